// The Write stream to one server (write_stream.h). Mirrors the Python
// client's client/write_stream.py.
#include "write_stream.h"

#include <algorithm>
#include <condition_variable>
#include <map>
#include <thread>
#include <utility>
#include <vector>

#include "conversions.h"
#include "durations.h"

namespace cast::detail {

namespace {

// How long a renewed token waits for the old stream's outstanding replies
// before its new stream opens (a lock may be waiting among them).
constexpr Millis kTokenDrain{30000};
// How long replacing a stream waits for the old one to end after its half-close.
constexpr Millis kEndGrace{2000};
// The writer puts queued requests together in a message up to this size
// (one larger request goes alone), so that many large values in flight never
// make a message over kMaxMessageBytes, which would end the stream.
constexpr std::size_t kMessageFill = 8 * 1024 * 1024;
// What a request may take on the wire at most: a message's limit, less room
// for the message's own framing.
constexpr std::size_t kMaxRequestBytes = kMaxMessageBytes - 64 * 1024;

// Puts `error` into `promise` as the exception of its own class.
template <class T>
void fail(std::promise<T>& promise, const CastError& error) {
  try {
    error.raise();
  } catch (...) {
    promise.set_exception(std::current_exception());
  }
}

std::string describe(const grpc::Status& status) {
  if (status.ok()) return "the server ended it";
  const std::string code = statusCodeName(static_cast<int>(status.error_code()));
  return status.error_message().empty() ? code : code + ": " + status.error_message();
}

// How an error names a request: "add of 'x'", "lock of 'x'", "batch of 3 writes".
std::string describe(const v1::WriteRequest& request) {
  switch (request.operation_case()) {
    case v1::WriteRequest::kAdd: return "add of '" + request.add().address().id() + "'";
    case v1::WriteRequest::kOverwrite: return "overwrite of '" + request.overwrite().address().id() + "'";
    case v1::WriteRequest::kDelete: return "delete of '" + request.delete_().address().id() + "'";
    case v1::WriteRequest::kBatch: return "batch of " + std::to_string(request.batch().operations_size()) + " writes";
    case v1::WriteRequest::kLock: return "lock of '" + request.lock().address().id() + "'";
    case v1::WriteRequest::kUnlock: return "unlock of '" + request.unlock().address().id() + "'";
    case v1::WriteRequest::kGet: return "get of '" + request.get().address().id() + "'";
    default: return "request";
  }
}

// What a request a thread waits for ends with: its reply, or the error it failed with (the reply's own
// error, when it carries one).
struct Outcome {
  v1::WriteReply reply;
  std::shared_ptr<CastError> error;
};

// The handler that settles `promise` with the request's outcome.
ReplyHandler settling(std::shared_ptr<std::promise<Outcome>> promise) {
  return [promise = std::move(promise)](const v1::WriteReply* reply, const std::shared_ptr<CastError>& failed) {
    promise->set_value(reply ? Outcome{*reply, replyError(*reply)} : Outcome{{}, failed});
  };
}

}  // namespace

std::shared_ptr<CastError> replyError(const v1::WriteReply& reply) {
  if (!reply.has_error()) return nullptr;
  const v1::WriteError& error = reply.error();
  return errorForCode(error.code(), error.message().empty() ? error.code() : error.message(), error.error_class());
}

// One open Write call: its outstanding requests, the requests waiting to be
// written, a thread writing them, a thread reading replies and a thread
// watching their deadlines.
struct WriteStream::Call {
  using Clock = std::chrono::steady_clock;

  Call(std::string endpoint, std::string token, Millis lookEvery)
      : endpoint(std::move(endpoint)), token(std::move(token)), lookEvery(lookEvery) {}
  ~Call() { join(); }

  // Starts the call; may wait for the connection (close() cancels it).
  void open(Server& server) {
    context.AddMetadata("authorization", "Bearer " + token);
    stream = server.wm->Write(&context);
    reader = std::thread([this] { read(); });
    writer = std::thread([this] { write(); });
    watcher = std::thread([this] { watch(); });
  }

  // Registers `request` under the next id and sends it (it is moved out);
  // false, with nothing taken, if the call broke or is closing.
  bool send(v1::WriteRequest& request, std::size_t size, ReplyHandler& onReply, bool direct,
            std::optional<Millis> timeout) {
    std::unique_lock<std::mutex> lock(mu);
    if (broken || halfClosed) return false;
    request.set_id(nextId++);
    pending.emplace(request.id(), std::move(onReply));
    if (timeout) {
      const Clock::time_point at = Clock::now() + *timeout;
      deadlines.emplace(request.id(), Deadline{at, *timeout, describe(request)});
      sent = true;
      // The watcher sleeps until its earliest deadline; only an earlier one wakes it.
      if (!watchUntil || at < *watchUntil) deadlineWake.notify_one();
    }
    if (!direct || writing || !queued.empty()) {
      queued.emplace_back(std::move(request), size);
      wake.notify_one();
      return true;
    }
    // Nothing else to send: written from here, without waking the writer.
    writing = true;
    lock.unlock();
    v1::WriteRequests message;
    message.add_requests()->Swap(&request);
    // A failed write means the call broke: the reader then fails what is
    // outstanding, this request included.
    stream->Write(message);
    lock.lock();
    writing = false;
    wake.notify_one();
    return true;
  }

  // The writer thread: what is queued goes in one message (up to
  // kMessageFill), one message at a time; after a half-close, what is left
  // and then the end.
  void write() {
    std::unique_lock<std::mutex> lock(mu);
    for (;;) {
      wake.wait(lock, [this] { return broken || (!writing && (!queued.empty() || halfClosed)); });
      if (broken) return;
      writing = true;
      if (queued.empty()) {
        lock.unlock();
        stream->WritesDone();
        return;
      }
      v1::WriteRequests message;
      std::size_t taken = 0;
      std::size_t bytes = 0;
      while (taken < queued.size() && (taken == 0 || bytes + queued[taken].second <= kMessageFill)) {
        bytes += queued[taken].second;
        *message.add_requests() = std::move(queued[taken].first);
        ++taken;
      }
      queued.erase(queued.begin(), queued.begin() + static_cast<std::ptrdiff_t>(taken));
      lock.unlock();
      stream->Write(message);
      lock.lock();
      writing = false;
    }
  }

  // The reader thread: answers each request by id; when the call ends, fails
  // what is still outstanding.
  void read() {
    v1::WriteReplies message;
    while (stream->Read(&message)) {
      std::vector<std::pair<ReplyHandler, const v1::WriteReply*>> answered;
      {
        std::lock_guard<std::mutex> lock(mu);
        for (const auto& reply : message.replies()) {
          deadlines.erase(reply.id());
          auto it = pending.find(reply.id());
          if (it == pending.end()) continue;  // its deadline passed: its sender has the error
          answered.emplace_back(std::move(it->second), &reply);
          pending.erase(it);
        }
        if (pending.empty()) changed.notify_all();
      }
      for (auto& [handler, reply] : answered) handler(reply, nullptr);
    }
    const grpc::Status status = stream->Finish();
    std::map<std::uint64_t, ReplyHandler> left;
    std::string why;  // the watcher's reason, or the status
    bool endedByWatcher = false;
    {
      std::lock_guard<std::mutex> lock(mu);
      broken = true;
      left.swap(pending);
      queued.clear();
      deadlines.clear();
      endedByWatcher = !stalled.empty();
      why = endedByWatcher ? stalled : describe(status);
      wake.notify_all();
      deadlineWake.notify_all();
    }
    std::shared_ptr<CastError> error;
    if (status.error_code() == grpc::StatusCode::UNAUTHENTICATED && !endedByWatcher) {
      // The server refused the token the call was opened with: it applied
      // none of its requests, which fail as a refused unary call would.
      error = errorForStatus(status, errorTrailer(context.GetServerTrailingMetadata()));
    } else {
      error = std::make_shared<UnavailableError>(
          "the write stream to " + endpoint + " broke (" + why +
          "): this write may or may not have been applied; the client reconnects by itself, retry the call later");
    }
    for (auto& kv : left) kv.second(nullptr, error);
    std::lock_guard<std::mutex> lock(mu);
    ended = true;
    changed.notify_all();
  }

  // The watcher thread: ends the call when an outstanding request passes its
  // deadline (write_stream.h). It sleeps until the earliest deadline; while
  // requests are sent it looks again every `lookEvery`, so that a sender need
  // not wake it each time.
  void watch() {
    std::unique_lock<std::mutex> lock(mu);
    Clock::time_point now;
    for (;;) {
      if (broken) return;
      now = Clock::now();
      std::optional<Clock::time_point> until;
      if (!deadlines.empty()) {
        const auto oldest = std::min_element(deadlines.begin(), deadlines.end(),
                                             [](const auto& a, const auto& b) { return a.second.at < b.second.at; });
        if (oldest->second.at <= now) break;
        until = oldest->second.at;
      } else if (sent) {
        until = now + lookEvery;
      }
      sent = false;
      watchUntil = until;
      if (until) {
        deadlineWake.wait_until(lock, *until);
      } else {
        deadlineWake.wait(lock);
      }
    }
    std::vector<std::pair<ReplyHandler, std::shared_ptr<CastError>>> expired;
    for (auto it = deadlines.begin(); it != deadlines.end();) {
      if (it->second.at > now) {
        ++it;
        continue;
      }
      const Deadline& d = it->second;
      if (stalled.empty()) {
        stalled = endpoint + " answered no request within its deadline (" + d.what + " waited " + secondsText(d.timeout) +
                  "): the server looks hung, so the stream was ended";
      }
      auto p = pending.find(it->first);
      if (p != pending.end()) {
        expired.emplace_back(std::move(p->second),
                             std::make_shared<DeadlineExceededError>(
                                 "no reply from " + endpoint + " to the " + d.what + " within " + secondsText(d.timeout) +
                                 ": it may or may not have been applied; the write stream was ended and the next "
                                 "write opens a new one"));
        pending.erase(p);
      }
      it = deadlines.erase(it);
    }
    if (pending.empty()) changed.notify_all();
    lock.unlock();
    for (auto& [handler, error] : expired) handler(nullptr, error);
    context.TryCancel();  // the reader sees the end and fails the others
  }

  bool usable() {
    std::lock_guard<std::mutex> lock(mu);
    return !broken && !halfClosed;
  }

  // Waits up to `timeout` until no request is outstanding.
  void drain(Millis timeout) {
    std::unique_lock<std::mutex> lock(mu);
    changed.wait_for(lock, timeout, [this] { return pending.empty(); });
  }

  // Half-closes once what is queued is written, waits up to `grace` for the
  // server to end the call, and cancels it past that.
  void end(Millis grace) {
    std::unique_lock<std::mutex> lock(mu);
    halfClosed = true;
    wake.notify_all();
    if (!changed.wait_for(lock, grace, [this] { return ended; })) context.TryCancel();
  }

  void join() {
    for (std::thread* t : {&writer, &reader, &watcher}) {
      if (t->joinable() && t->get_id() != std::this_thread::get_id()) t->join();
    }
  }

  struct Deadline {
    Clock::time_point at;
    Millis timeout;
    std::string what;
  };

  const std::string endpoint;
  const std::string token;
  const Millis lookEvery;
  grpc::ClientContext context;
  std::unique_ptr<grpc::ClientReaderWriter<v1::WriteRequests, v1::WriteReplies>> stream;
  std::thread reader;
  std::thread writer;
  std::thread watcher;
  std::mutex mu;
  std::condition_variable wake;          // something to write, a write done, or the end: for the writer
  std::condition_variable changed;       // a reply came (pending shrank), or the call ended
  std::condition_variable deadlineWake;  // a deadline earlier than the watcher's, or the end
  std::map<std::uint64_t, ReplyHandler> pending;
  std::map<std::uint64_t, Deadline> deadlines;        // outstanding ids with a deadline
  std::optional<Clock::time_point> watchUntil;        // when the watcher looks next (nullopt: when told)
  bool sent = false;                                  // a request was sent since the watcher last looked
  std::string stalled;                                // why the watcher ended the call
  std::vector<std::pair<v1::WriteRequest, std::size_t>> queued;  // registered, waiting for the writer (with size)
  std::uint64_t nextId = 1;
  bool writing = false;     // a Write (or the half-close) is under way
  bool halfClosed = false;  // nothing more is accepted; the writer ends the sending side
  bool broken = false;      // the reader saw the end: nothing more is sent on it
  bool ended = false;       // the reader has failed what was outstanding and is done
};

WriteStream::WriteStream(Server& server, std::shared_ptr<TokenSource> tokens, Millis callTimeout)
    : server_(server), tokens_(std::move(tokens)), callTimeout_(callTimeout) {}

WriteStream::~WriteStream() { close(); }

// Called with openMu_ held: the call to send on, opened when there is none,
// it broke, or the token changed; nullptr once closed, or when no connection
// could be made within `connectWait` (`*unreachable` then true).
std::shared_ptr<WriteStream::Call> WriteStream::current(const std::string& token, Millis connectWait,
                                                        bool* unreachable) {
  std::shared_ptr<Call> call;
  {
    std::lock_guard<std::mutex> lock(stateMu_);
    if (closed_) return nullptr;
    call = call_;
  }
  if (call && call->usable() && call->token == token) return call;
  if (call) {
    // A renewed token: the new stream must not overtake the old one's
    // writes. A broken call just ends (its reader fails what it had).
    call->drain(call->usable() ? kTokenDrain : Millis(0));
    call->end(kEndGrace);
    call->join();
  }
  // Opening a call waits while the channel connects, as long as gRPC's
  // connect timeout (20 s) when the server accepts TCP but answers nothing:
  // bounded here, so that a write ends by its deadline. A channel that failed
  // to connect (the server is away) fails the call at once, as before.
  const auto until = std::chrono::system_clock::now() + connectWait;
  for (auto state = server_.channel->GetState(true);
       state == GRPC_CHANNEL_IDLE || state == GRPC_CHANNEL_CONNECTING; state = server_.channel->GetState(true)) {
    if (!server_.channel->WaitForStateChange(state, until)) {
      *unreachable = true;
      return nullptr;
    }
  }
  auto fresh = std::make_shared<Call>(server_.endpoint, token, callTimeout_);
  {
    std::lock_guard<std::mutex> lock(stateMu_);
    if (closed_) return nullptr;
    call_ = fresh;
  }
  fresh->open(server_);
  return fresh;
}

std::shared_ptr<ClientSession> WriteStream::send(v1::WriteRequest& request, ReplyHandler onReply, bool direct,
                                                std::optional<Millis> timeout) {
  // Refused here, not by gRPC: a message over the limit would end the stream
  // and fail every write in flight with it.
  const std::size_t size = request.ByteSizeLong();
  if (size > kMaxRequestBytes) {
    onReply(nullptr, std::make_shared<InvalidArgumentError>(
                         "a write of " + std::to_string(size) + " bytes is over the " +
                         std::to_string(kMaxRequestBytes) + "-byte limit of one request on the connection to " +
                         server_.endpoint + " (gRPC messages up to 64 MiB); the server takes values up to its "
                         "limits.max_value_bytes (8 MiB by default): keep large data elsewhere and write a "
                         "reference to it"));
    return nullptr;
  }
  // The session's socket while there is a session (opened on the way if
  // needed, within the request's time): after what the gRPC call has
  // outstanding, so that no request overtakes an earlier one.
  const std::string token = tokens_->token();
  if (server_.shared) {
    // A renewed token: a session says it in its HELLO, so a new one opens (after the old one's replies).
    std::shared_ptr<ClientSession> session = server_.shared->writerSession(timeout.value_or(callTimeout_));
    if (session) {
      if (!drainCall()) {
        onReply(nullptr, std::make_shared<UnavailableError>("the connection to " + server_.endpoint +
                                                            " is closed: no more writes"));
        return nullptr;
      }
      if (session->writes().send(request, onReply, timeout, direct)) return direct ? session : nullptr;
      // The session ended just now: the gRPC stream takes it.
    }
  }
  // Twice at most: a call that broke (or was replaced) just now gives way to a new one.
  for (int attempt = 0; attempt < 2; ++attempt) {
    std::shared_ptr<Call> call;
    bool unreachable = false;
    {
      std::lock_guard<std::mutex> lock(openMu_);
      call = current(token, timeout.value_or(callTimeout_), &unreachable);
    }
    if (unreachable) {
      onReply(nullptr, std::make_shared<UnavailableError>(
                           "the write stream to " + server_.endpoint + " could not be opened: the server "
                           "completed no connection within " + secondsText(timeout.value_or(callTimeout_)) +
                           ", so this write was not sent; the client reconnects by itself, retry the call later"));
      return nullptr;
    }
    if (!call) {
      onReply(nullptr, std::make_shared<UnavailableError>("the connection to " + server_.endpoint +
                                                          " is closed: no more writes"));
      return nullptr;
    }
    if (call->send(request, size, onReply, direct, timeout)) return nullptr;
  }
  onReply(nullptr, std::make_shared<UnavailableError>("the write stream to " + server_.endpoint +
                                                      " broke twice while this write was sent: it was not applied; "
                                                      "the client reconnects by itself, retry the call later"));
  return nullptr;
}

v1::WriteReply WriteStream::call(v1::WriteRequest request, std::optional<Millis> timeout) {
  // A token that can be renewed (a token file) may be refused and the
  // request sent again: keep a copy for that only then, values may be large.
  std::optional<v1::WriteRequest> again;
  if (!tokens_->path().empty()) again = request;
  for (int attempt = 0;; ++attempt) {
    auto promise = std::make_shared<std::promise<Outcome>>();
    std::future<Outcome> future = promise->get_future();
    // Answered by the reply, or by the call's watcher past `timeout` (DeadlineExceededError).
    std::shared_ptr<ClientSession> on = send(attempt == 0 ? request : *again, settling(promise), true, timeout);
    // On the session's socket this thread reads its reply itself while no other thread reads there.
    if (on) on->writes().await([&future] { return future.wait_for(Millis(0)) == std::future_status::ready; });
    Outcome outcome = future.get();
    if (!outcome.error) return std::move(outcome.reply);
    // A refused token may just have been renewed in its file: read it and
    // send once more (on a stream opened with the new token).
    // (A session's writes carry its HELLO's token: send() opens a new session with the new one.)
    if (attempt == 0 && again && outcome.error->code() == "UNAUTHENTICATED" && tokens_->refresh()) continue;
    outcome.error->raise();
  }
}

bool WriteStream::drainCall() {
  std::shared_ptr<Call> grpcCall;
  {
    std::lock_guard<std::mutex> lock(stateMu_);
    if (closed_) return false;
    grpcCall = call_;
  }
  if (grpcCall) grpcCall->drain(kTokenDrain);  // at once when nothing is outstanding (queued ones are too)
  return true;
}

std::optional<v1::WriteReply> WriteStream::read(ClientSession& session, v1::WriteRequest request,
                                                std::optional<Millis> timeout) {
  // The read sees the writes the gRPC call still has outstanding.
  if (!drainCall()) throw UnavailableError("the connection to " + server_.endpoint + " is closed: no more calls");
  auto promise = std::make_shared<std::promise<Outcome>>();
  std::future<Outcome> future = promise->get_future();
  ReplyHandler onReply = settling(promise);
  if (!session.writes().send(request, onReply, timeout, true)) return std::nullopt;
  // This thread reads its reply itself while no other thread reads the socket.
  session.writes().await([&future] { return future.wait_for(Millis(0)) == std::future_status::ready; });
  Outcome outcome = future.get();
  if (outcome.error) outcome.error->raise();
  return std::move(outcome.reply);
}

std::future<WriteResult> WriteStream::writeAsync(v1::WriteRequest request,
                                                 std::function<void(const std::shared_ptr<CastError>&)> finished,
                                                 std::optional<Millis> timeout) {
  auto promise = std::make_shared<std::promise<WriteResult>>();
  std::future<WriteResult> future = promise->get_future();
  send(request,
       [promise, finished = std::move(finished)](const v1::WriteReply* reply,
                                                  const std::shared_ptr<CastError>& failed) {
         const std::shared_ptr<CastError> error = reply ? replyError(*reply) : failed;
         if (finished) finished(error);
         if (error) {
           fail(*promise, *error);
         } else {
           promise->set_value(writeResult(reply->write()));
         }
       },
       false, timeout ? *timeout : callTimeout_);
  return future;
}

void WriteStream::close(Millis grace) {
  std::shared_ptr<Call> call;
  {
    std::lock_guard<std::mutex> lock(stateMu_);
    if (closed_) return;
    closed_ = true;
    call = call_;
  }
  // The session's outstanding writes are answered before the transport ends the session.
  if (server_.shared) {
    if (std::shared_ptr<ClientSession> session = server_.shared->current()) session->writes().drain(grace);
  }
  if (!call) return;
  call->drain(grace);
  call->end(grace);
  // A call still opening (waiting for the connection) was cancelled by
  // end(): its opener returns, and its threads can be joined.
  std::lock_guard<std::mutex> lock(openMu_);
  call->join();
}

}  // namespace cast::detail
