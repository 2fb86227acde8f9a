// The Watch bidi stream to one server (docs/client-protocol.md, "Watching"
// and "Reconnecting"): private to the gRPC transport, which keeps one per
// server and fans each onChange out to the streams of the servers involved.
#pragma once

#include <atomic>
#include <condition_variable>
#include <cstdint>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include "backoff.h"
#include "cast/log.h"
#include "transport.h"
#include "grpc_server.h"

namespace cast::detail {

// One Watch call to one server, shared by every watch of the component there.
//
// When the connection breaks the stream is opened again with backoff and
// every watch is created again from the revision after the last one it got
// (per SA): no gap and no duplicate. The server's history id goes along, so a
// server that lost that history (restarted without persistence) refuses the
// resume, and the component is told to resynchronise (watchFailed with
// HistoryExpiredError).
//
// On the server's host the stream asks to be lent large values (shm.h): it
// is a read call of the shared-memory session, whose end says what arrived.
// A stream opened while no session could be had (its server was away) is
// opened again once one is, resuming where it was.
//
// With a session, and a component that said how (SocketEvents), the call
// asks for its event batches as EVENTS frames on the session's socket
// (docs/client-protocol.md, "A watch's events on the session's socket"): the
// component's dispatcher thread reads the session's socket (dispatcher.h),
// turns each frame into events and runs their callbacks, with no other
// thread between (the session's reader thread does it in its place while it
// reads for pipelined writes, queueing the callbacks); the
// call carries the rest (created, failed, its end). When the socket ends, or
// a frame's value cannot be claimed, the call is ended and opened again from
// the revision after the last event queued: what was read was queued, what
// was not comes again on the new call.
struct SocketEvents {
  EventSink now;  // queues without waiting (the reader looked for room first)
  std::function<bool(std::chrono::milliseconds)> room;
  AttachSource attach;  // hands the session to the component's dispatcher thread
};

class WatchStream {
 public:
  // Starts the reader thread, which opens the stream (and reopens it after a
  // break). `sink` gets every event, `onError` a failure that ends watches;
  // `socket`, if set, the events of a call that takes them on the session's
  // socket.
  WatchStream(Server& server, std::shared_ptr<TokenSource> tokens, EventSink sink, ErrorSink onError,
              SocketEvents socket = {});
  ~WatchStream();
  WatchStream(const WatchStream&) = delete;
  WatchStream& operator=(const WatchStream&) = delete;

  // True once the stream ended for good (an error that is not transient):
  // the transport then opens a new one for later watches.
  bool dead();
  // Creates watch `watchId` on this server and waits up to `timeout` for the
  // server to confirm it; returns the revision per SA it starts after.
  std::map<std::string, std::uint64_t> create(std::uint32_t watchId, const std::vector<ChangeFilter>& filters,
                                              const std::map<std::string, std::uint64_t>& starts, Delivery delivery,
                                              Millis timeout);
  // Forgets a watch and tells the server (if the stream is open).
  void cancel(std::uint32_t watchId);
  // Ends the stream and joins the reader; creates still waiting fail with CANCELLED.
  void close();

 private:
  // A create waiting for the server's created or failed.
  struct Pending {
    bool done = false;
    std::map<std::string, std::uint64_t> revisions;
    std::shared_ptr<CastError> error;
  };

  // What the client keeps of one watch to create it again after a reconnect.
  struct Watch {
    std::uint32_t watchId = 0;
    std::vector<ChangeFilter> filters;
    Delivery delivery = Delivery::Queue;
    std::map<std::string, std::uint64_t> firstStarts;
    std::vector<std::string> sas;  // the SAs of this server the watch covers (known once created)
    // Per SA, the revision the watch is known to have seen up to (unset until created).
    std::optional<std::map<std::string, std::uint64_t>> base;
  };

  v1::WatchRequest createRequest(Watch& w);
  bool write(const v1::WatchRequest& request);
  void resolve(std::uint32_t watchId, std::map<std::string, std::uint64_t> revisions,
               std::shared_ptr<CastError> error);
  void run();
  void handle(const v1::WatchResponse& response);
  void fail(const std::shared_ptr<CastError>& error);
  // An EVENTS frame's batch of `call`, on the session's reader thread.
  void socketBatch(const ReadCall* call, const char* data, std::size_t size);
  // The session carrying `call`'s events ended, or one of them could not be
  // read: the call ends, and is opened again.
  void breakCall(const ReadCall* call, const std::string& why);

  Server& server_;
  std::shared_ptr<TokenSource> tokens_;
  EventSink sink_;
  ErrorSink onError_;
  Logger log_;
  std::mutex mu_;
  std::condition_variable cv_;
  std::shared_ptr<grpc::ClientContext> context_;
  std::shared_ptr<grpc::ClientReaderWriter<v1::WatchRequest, v1::WatchResponse>> stream_;
  std::map<std::uint32_t, std::shared_ptr<Watch>> watches_;
  std::map<std::uint32_t, std::shared_ptr<Pending>> pending_;
  std::map<std::string, std::uint64_t> seen_;  // newest revision per SA received on this stream
  std::string historyId_;
  std::atomic<bool> connected_{false};
  bool dead_ = false;
  bool closed_ = false;
  std::shared_ptr<CastError> deathError_;
  SocketEvents socket_;
  // The open call's part of the shared-memory session: set by the stream's
  // thread, under framesMu_, which a batch from the socket holds too.
  std::unique_ptr<ReadCall> read_;
  std::mutex framesMu_;
  std::atomic<const ReadCall*> onSocket_{nullptr};  // the call whose events come on the socket now
  std::mutex brokenMu_;  // guards broken_ (told from wherever the session ends)
  std::string broken_;   // why the call taking its events on the socket must end
  Closing closing_;
  std::thread thread_;
};

}  // namespace cast::detail
