// One server of a system as the gRPC transport reaches it, and the unary call
// that every part of the transport makes. Shared by grpc_transport.cc (routing
// and the unary calls), watch_stream.cc and session.cc, which each open their
// own streams on a server's channel.
#pragma once

#include <grpcpp/grpcpp.h>

#include <chrono>
#include <memory>
#include <optional>
#include <string>
#include <utility>

#include "cast/credentials.h"
#include "cast/errors.h"
#include "cast/v1/directory.grpc.pb.h"
#include "cast/v1/inspection.grpc.pb.h"
#include "cast/v1/task_manager.grpc.pb.h"
#include "cast/v1/working_memory.grpc.pb.h"
#include "shm.h"

namespace cast::detail {

// The largest gRPC message either way (servers set the same). Large values
// (images, point clouds) must pass; gRPC's default is 4 MB.
inline constexpr int kMaxMessageBytes = 64 * 1024 * 1024;

// The channel credentials for `tls` (plaintext without); sets the name to
// verify the server's certificate against in `args`. InvalidArgumentError for
// a TLS file that cannot be read. Defined in credentials.cc.
std::shared_ptr<grpc::ChannelCredentials> channelCredentials(const std::optional<ClientTls>& tls,
                                                             grpc::ChannelArguments& args);

// One server: its channel and a stub per service. Its streams belong to
// whoever opened them (the watch stream, the session, the decision stream).
struct Server {
  // Dials `endpoint` (the channel connects lazily, on the first call).
  Server(std::string endpoint, const std::optional<ClientTls>& tls);

  std::string endpoint;
  std::shared_ptr<grpc::Channel> channel;
  std::unique_ptr<v1::WorkingMemory::Stub> wm;
  std::unique_ptr<v1::TaskManager::Stub> tm;
  std::unique_ptr<v1::Directory::Stub> dir;
  std::unique_ptr<v1::Inspection::Stub> insp;  // Report: the component's outcomes
  // Shared memory with this server when on its host (shm.h), opened when
  // first needed; set by the transport right after the server is made.
  std::shared_ptr<SharedLink> shared;
};

// The metadata every call carries: the component's token.
inline void authorize(grpc::ClientContext& context, TokenSource& tokens) {
  context.AddMetadata("authorization", "Bearer " + tokens.token());
}

// One unary call with the token and a deadline (nullopt: none); a failed
// status becomes the named error (the precise one the server's trailer names). `fn(context, response)` makes the call.
template <class Resp, class Fn>
Resp unaryCall(TokenSource& tokens, std::optional<std::chrono::milliseconds> deadline, Fn&& fn) {
  for (int attempt = 0;; ++attempt) {
    grpc::ClientContext ctx;
    authorize(ctx, tokens);
    if (deadline) ctx.set_deadline(std::chrono::system_clock::now() + *deadline);
    Resp resp;
    const grpc::Status status = fn(&ctx, &resp);
    if (status.ok()) return resp;
    // A refused token may just have been renewed in its file: read it and
    // try once more.
    if (attempt == 0 && status.error_code() == grpc::StatusCode::UNAUTHENTICATED && tokens.refresh()) continue;
    errorForStatus(status, errorTrailer(ctx.GetServerTrailingMetadata()))->raise();
  }
}

}  // namespace cast::detail
