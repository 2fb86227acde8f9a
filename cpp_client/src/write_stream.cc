// The Write stream to one server (write_stream.h). Mirrors the Python
// client's client/write_stream.py.
#include "write_stream.h"

#include <condition_variable>
#include <map>
#include <thread>
#include <utility>
#include <vector>

#include "conversions.h"

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

}  // namespace

std::shared_ptr<CastError> replyError(const v1::WriteReply& reply) {
  if (!reply.has_error()) return nullptr;
  const v1::WriteError& error = reply.error();
  return errorForCode(error.code(), error.message().empty() ? error.code() : error.message(), error.error_class());
}

// One open Write call: its outstanding requests, the requests waiting to be
// written, a thread writing them and a thread reading replies.
struct WriteStream::Call {
  Call(std::string endpoint, std::string token) : endpoint(std::move(endpoint)), token(std::move(token)) {}
  ~Call() { join(); }

  // Starts the call; may wait for the connection (close() cancels it).
  void open(Server& server) {
    context.AddMetadata("authorization", "Bearer " + token);
    stream = server.wm->Write(&context);
    reader = std::thread([this] { read(); });
    writer = std::thread([this] { write(); });
  }

  // Registers `request` under the next id and sends it (it is moved out);
  // false, with nothing taken, if the call broke or is closing.
  bool send(v1::WriteRequest& request, std::size_t size, ReplyHandler& onReply, bool direct) {
    std::unique_lock<std::mutex> lock(mu);
    if (broken || halfClosed) return false;
    request.set_id(nextId++);
    pending.emplace(request.id(), std::move(onReply));
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
          auto it = pending.find(reply.id());
          if (it == pending.end()) continue;
          answered.emplace_back(std::move(it->second), &reply);
          pending.erase(it);
        }
        if (pending.empty()) changed.notify_all();
      }
      for (auto& [handler, reply] : answered) handler(reply, nullptr);
    }
    const grpc::Status status = stream->Finish();
    std::map<std::uint64_t, ReplyHandler> left;
    {
      std::lock_guard<std::mutex> lock(mu);
      broken = true;
      left.swap(pending);
      queued.clear();
      wake.notify_all();
    }
    std::shared_ptr<CastError> error;
    if (status.error_code() == grpc::StatusCode::UNAUTHENTICATED) {
      // The server refused the token the call was opened with: it applied
      // none of its requests, which fail as a refused unary call would.
      error = errorForStatus(status, errorTrailer(context.GetServerTrailingMetadata()));
    } else {
      error = std::make_shared<UnavailableError>(
          "the write stream to " + endpoint + " broke (" + describe(status) +
          "): this write may or may not have been applied; the client reconnects by itself, retry the call later");
    }
    for (auto& kv : left) kv.second(nullptr, error);
    std::lock_guard<std::mutex> lock(mu);
    ended = true;
    changed.notify_all();
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
    for (std::thread* t : {&writer, &reader}) {
      if (t->joinable() && t->get_id() != std::this_thread::get_id()) t->join();
    }
  }

  const std::string endpoint;
  const std::string token;
  grpc::ClientContext context;
  std::unique_ptr<grpc::ClientReaderWriter<v1::WriteRequests, v1::WriteReplies>> stream;
  std::thread reader;
  std::thread writer;
  std::mutex mu;
  std::condition_variable wake;     // something to write, a write done, or the end: for the writer
  std::condition_variable changed;  // a reply came (pending shrank), or the call ended
  std::map<std::uint64_t, ReplyHandler> pending;
  std::vector<std::pair<v1::WriteRequest, std::size_t>> queued;  // registered, waiting for the writer (with size)
  std::uint64_t nextId = 1;
  bool writing = false;     // a Write (or the half-close) is under way
  bool halfClosed = false;  // nothing more is accepted; the writer ends the sending side
  bool broken = false;      // the reader saw the end: nothing more is sent on it
  bool ended = false;       // the reader has failed what was outstanding and is done
};

WriteStream::WriteStream(Server& server, std::shared_ptr<TokenSource> tokens)
    : server_(server), tokens_(std::move(tokens)) {}

WriteStream::~WriteStream() { close(); }

// Called with openMu_ held: the call to send on, opened when there is none,
// it broke, or the token changed; nullptr once closed.
std::shared_ptr<WriteStream::Call> WriteStream::current(const std::string& token) {
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
  auto fresh = std::make_shared<Call>(server_.endpoint, token);
  {
    std::lock_guard<std::mutex> lock(stateMu_);
    if (closed_) return nullptr;
    call_ = fresh;
  }
  fresh->open(server_);
  return fresh;
}

void WriteStream::send(v1::WriteRequest& request, ReplyHandler onReply, bool direct) {
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
    return;
  }
  const std::string token = tokens_->token();
  // Twice at most: a call that broke (or was replaced) just now gives way to a new one.
  for (int attempt = 0; attempt < 2; ++attempt) {
    std::shared_ptr<Call> call;
    {
      std::lock_guard<std::mutex> lock(openMu_);
      call = current(token);
    }
    if (!call) {
      onReply(nullptr, std::make_shared<UnavailableError>("the connection to " + server_.endpoint +
                                                          " is closed: no more writes"));
      return;
    }
    if (call->send(request, size, onReply, direct)) return;
  }
  onReply(nullptr, std::make_shared<UnavailableError>("the write stream to " + server_.endpoint +
                                                      " broke twice while this write was sent: it was not applied; "
                                                      "the client reconnects by itself, retry the call later"));
}

v1::WriteReply WriteStream::call(v1::WriteRequest request, std::optional<Millis> timeout) {
  // A token that can be renewed (a token file) may be refused and the
  // request sent again: keep a copy for that only then, values may be large.
  std::optional<v1::WriteRequest> again;
  if (!tokens_->path().empty()) again = request;
  struct Outcome {
    v1::WriteReply reply;
    std::shared_ptr<CastError> error;
  };
  for (int attempt = 0;; ++attempt) {
    auto promise = std::make_shared<std::promise<Outcome>>();
    std::future<Outcome> future = promise->get_future();
    send(attempt == 0 ? request : *again,
         [promise](const v1::WriteReply* reply, const std::shared_ptr<CastError>& failed) {
           promise->set_value(reply ? Outcome{*reply, replyError(*reply)} : Outcome{{}, failed});
         },
         true);
    if (timeout && future.wait_for(*timeout) != std::future_status::ready) {
      throw DeadlineExceededError("no reply from " + server_.endpoint + " to a write within " +
                                  std::to_string(timeout->count()) + " ms: it may or may not have been applied");
    }
    Outcome outcome = future.get();
    if (!outcome.error) return std::move(outcome.reply);
    // A refused token may just have been renewed in its file: read it and
    // send once more (on a stream opened with the new token).
    if (attempt == 0 && again && outcome.error->code() == "UNAUTHENTICATED" && tokens_->refresh()) continue;
    outcome.error->raise();
  }
}

std::future<WriteResult> WriteStream::writeAsync(v1::WriteRequest request) {
  auto promise = std::make_shared<std::promise<WriteResult>>();
  std::future<WriteResult> future = promise->get_future();
  send(request,
       [promise](const v1::WriteReply* reply, const std::shared_ptr<CastError>& failed) {
         if (!reply) {
           fail(*promise, *failed);
         } else if (auto error = replyError(*reply)) {
           fail(*promise, *error);
         } else {
           promise->set_value(writeResult(reply->write()));
         }
       },
       false);
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
  if (!call) return;
  call->drain(grace);
  call->end(grace);
  // A call still opening (waiting for the connection) was cancelled by
  // end(): its opener returns, and its threads can be joined.
  std::lock_guard<std::mutex> lock(openMu_);
  call->join();
}

}  // namespace cast::detail
