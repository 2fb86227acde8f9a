// A component's writes and locks on one WorkingMemory.Write stream per server
// (docs/client-protocol.md, "Write stream"): private to the gRPC transport,
// which sends every add, overwrite, delete, batch, lock and unlock here.
// Mirrors the Python client's client/write_stream.py.
//
// A unary call costs a whole gRPC call each way; on the stream a write is
// part of a message each way, and many may be in flight (send() returns at
// once, the reply comes later, matched by id). A message carries every
// request queued while the one before it was being written, so writes in
// flight share the cost of a message (WriteRequests). Writes are sent in call
// order on one stream, which the server applies in arrival order, so a
// component's writes keep their order.
//
// While the component has a shared-memory session with the server (shm.h),
// every request goes on the session's socket instead (socket_writes.h: the
// same messages in WRITES and REPLIES frames, without gRPC's threads on
// either side): all of them, so that their order stays the component's; a
// switch from one path to the other waits until the requests outstanding on
// the first are answered. When the session ends its outstanding requests
// fail with UnavailableError and the next write opens a new session, or goes
// on the gRPC stream when none can be opened. A get goes there too
// (read()): a frame each way costs a fraction of a unary call.
//
// The stream is opened on the first write. The token is checked before each
// send (TokenSource stats its file at most once a second): when it was
// renewed, the stream is replaced by one opened with the new token, after the
// old one's outstanding requests were answered (so no write overtakes an
// earlier one). A stream that breaks fails its outstanding requests with
// UnavailableError, as a broken unary call, and the next write opens a new
// one.
//
// Every request has a deadline (the call timeout; a blocking lock's own
// timeout plus a margin). A thread per stream watches them: when the oldest
// outstanding request passes its deadline, its sender gets
// DeadlineExceededError and the stream is ended (its other requests fail with
// UnavailableError), since a server that answers nothing in that time is hung,
// or the path to it is; keepalive alone notices that only when the
// connection's ping goes unanswered.
#pragma once

#include <chrono>
#include <cstdint>
#include <functional>
#include <future>
#include <memory>
#include <mutex>
#include <optional>
#include <string>

#include "backoff.h"
#include "grpc_server.h"
#include "socket_writes.h"

namespace cast::detail {

// The error a reply carries, as the unary call would have thrown it (the
// precise class the server named); nullptr for a reply with a result.
std::shared_ptr<CastError> replyError(const v1::WriteReply& reply);

class WriteStream {
 public:
  // `callTimeout`: the deadline of an asynchronous write.
  WriteStream(Server& server, std::shared_ptr<TokenSource> tokens, Millis callTimeout);
  ~WriteStream();
  WriteStream(const WriteStream&) = delete;
  WriteStream& operator=(const WriteStream&) = delete;

  // Sends `request` (its id is set here) and calls `onReply` once, on the
  // stream's reader or deadline thread or right here: keep it short, it holds
  // up the replies behind it. `direct`: when nothing else is being sent, write
  // it from this thread at once (a caller that waits for the reply); otherwise
  // it goes to the stream's writer thread with whatever queues up behind it.
  // Past `timeout` (nullopt: none) it is answered DeadlineExceededError and
  // the stream ends. The session whose socket it went on when `direct`, for
  // the caller to read its reply there (SessionWrites::await); nullptr
  // otherwise.
  std::shared_ptr<ClientSession> send(v1::WriteRequest& request, ReplyHandler onReply, bool direct,
                                      std::optional<Millis> timeout);
  // Sends `request` and waits up to `timeout` (nullopt: as long as it takes)
  // for its reply, DeadlineExceededError past it. A reply's error is thrown as
  // the unary call would throw it; a refused token is read again from its
  // file once, and the request sent again if it changed (a refused request
  // changed nothing).
  v1::WriteReply call(v1::WriteRequest request, std::optional<Millis> timeout);
  // Sends an add or overwrite and returns at once: the future of its result,
  // or of the error call() would have thrown. `finished`, if given, is called
  // with that error (nullptr for a result) just before the future completes
  // (the transport frees the write's shared-memory staging there). Past
  // `timeout` (nullopt: the call timeout) it fails with DeadlineExceededError.
  std::future<WriteResult> writeAsync(v1::WriteRequest request,
                                      std::function<void(const std::shared_ptr<CastError>&)> finished = nullptr,
                                      std::optional<Millis> timeout = std::nullopt);
  // Sends a read (a get) on `session`'s socket, after the writes this stream
  // has outstanding on its gRPC call (so that it sees them), and waits up to
  // `timeout` for its reply: nullopt when the session ended before it was
  // sent (the caller makes the unary call). Only `session`, the one its read
  // call names: a value lent on that call belongs to it. The reply's error is
  // thrown as the unary call would throw it.
  std::optional<v1::WriteReply> read(ClientSession& session, v1::WriteRequest request, std::optional<Millis> timeout);
  // Stops sending (later writes fail with UnavailableError), waits up to
  // `grace` for the outstanding replies, then ends the stream.
  void close(Millis grace = Millis(2000));

 private:
  struct Call;
  std::shared_ptr<Call> current(const std::string& token, Millis connectWait, bool* unreachable);
  // Waits until the gRPC call has nothing outstanding, so that no request on
  // the session's socket overtakes one still there; false once the stream is
  // closed.
  bool drainCall();

  Server& server_;
  std::shared_ptr<TokenSource> tokens_;
  Millis callTimeout_;
  std::mutex openMu_;   // held while choosing, replacing or opening the call
  std::mutex stateMu_;  // guards call_ and closed_ (close() takes it without waiting for an opening)
  std::shared_ptr<Call> call_;
  bool closed_ = false;
};

}  // namespace cast::detail
