// A component's Write-stream requests on its shared-memory session's Unix
// socket (docs/client-protocol.md, "Writes on the session's socket"): WRITES
// frames out, REPLIES frames in. Private to the gRPC transport: the Write
// stream (write_stream.h) sends here instead of on its gRPC call while the
// session with that server lives, and its gets too when the server answers
// them here (WriteStream::read). Mirrors the server's
// server/socket_writes.py.
//
// The same messages as the Write stream (a WriteRequests, a WriteReplies),
// the same rules: replies matched by id, out of order when a lock waits.
// The session's reader thread, started by the first request, reads the
// replies and watches the requests' deadlines (expire()): a request past its
// deadline gets DeadlineExceededError and the session is ended, as the Write
// stream ends its call, so that its other requests fail with
// UnavailableError ("may or may not have been applied") and the next write
// opens a new session or goes by gRPC.
#pragma once

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <string>

#include "cast/errors.h"
#include "cast/v1/working_memory.pb.h"

namespace cast::detail {

// What a request's sender gets back: the reply (which may carry the error the
// unary call would have ended with), or, when no reply will come, the error
// why (the stream or the session broke, the connection is closed).
using ReplyHandler = std::function<void(const v1::WriteReply* reply, const std::shared_ptr<CastError>& failed)>;

class ClientSession;

class SessionWrites {
 public:
  SessionWrites(ClientSession& session, std::string endpoint);
  ~SessionWrites() = default;
  SessionWrites(const SessionWrites&) = delete;
  SessionWrites& operator=(const SessionWrites&) = delete;

  // Sends `request` (its id is set here) in a WRITES frame and calls
  // `onReply` once, from the session's thread, or here when the frame could
  // not be sent; past `timeout` (nullopt: none) DeadlineExceededError, and
  // the session ends. False, with nothing taken, once the session ended.
  // `waited`: the caller waits for the reply with await(), reading it
  // itself; otherwise (a pipelined write) the session's reader thread reads
  // it, started here if it is not running.
  bool send(v1::WriteRequest& request, ReplyHandler& onReply, std::optional<std::chrono::milliseconds> timeout,
            bool waited = false);
  // Returns once `answered()` (the reply of a request sent `waited` was
  // handled) or the session ended: reads the socket on this thread while no
  // other thread does, else waits for the one that does (it wakes this one
  // when it settles a reply or stops reading), and fails what passed its
  // deadline meanwhile (expire). So a sequential write costs no hand-off from
  // a reader thread, as in the Python client.
  void await(const std::function<bool()>& answered);
  // From the session: a thread stopped reading the socket; one waiting in
  // await() reads next.
  void readerLeft();
  // Waits up to `timeout` until no request is outstanding.
  void drain(std::chrono::milliseconds timeout);
  // Requests sent and not yet answered.
  std::size_t outstanding();
  // Requests sent on this socket so far (writes, locks, gets), for tests and
  // diagnostics.
  std::uint64_t sent() const { return sent_.load(std::memory_order_relaxed); }
  // Bytes of the WRITES frames sent on this socket so far, for tests and
  // diagnostics (a staged value's bytes are not among them).
  std::uint64_t sentBytes() const { return sentBytes_.load(std::memory_order_relaxed); }

  // From the session's reader thread: fails the requests past their
  // deadline (and then ends the session); how long until the next deadline.
  std::chrono::milliseconds expire();
  // From the session: a REPLIES frame's body (ProtocolError if it does not
  // parse), and the session's end (what is outstanding fails).
  void replies(const std::string& body);
  void ended(const std::string& why);

 private:
  using Clock = std::chrono::steady_clock;
  struct Pending {
    ReplyHandler onReply;
    std::optional<Clock::time_point> deadline;
    std::chrono::milliseconds timeout{0};
  };

  ClientSession& session_;
  const std::string endpoint_;
  std::mutex mu_;
  std::condition_variable changed_;  // a reply came, or the session ended
  std::map<std::uint64_t, Pending> pending_;
  std::atomic<int> followers_{0};  // threads in await() waiting for another reader
  std::atomic<std::uint64_t> sent_{0};  // sent()
  std::atomic<std::uint64_t> sentBytes_{0};  // sentBytes()
  std::uint64_t nextId_ = 1;
  bool ended_ = false;
};

}  // namespace cast::detail
