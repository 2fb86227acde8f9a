// The Watch stream to one server (watch_stream.h). Mirrors the Python
// client's client/watch_stream.py.
#include "watch_stream.h"

#include <algorithm>
#include <cstdint>
#include <string>

#include "conversions.h"

namespace cast::detail {

WatchStream::WatchStream(Server& server, std::shared_ptr<TokenSource> tokens, EventSink sink, ErrorSink onError,
                         SocketEvents socket)
    : server_(server), tokens_(std::move(tokens)), sink_(std::move(sink)), onError_(std::move(onError)),
      log_("cast.client.watch"), socket_(std::move(socket)) {
  thread_ = std::thread([this] { run(); });
}

WatchStream::~WatchStream() { close(); }

bool WatchStream::dead() {
  std::lock_guard<std::mutex> lock(mu_);
  return dead_;
}

std::map<std::string, std::uint64_t> WatchStream::create(std::uint32_t watchId,
                                                         const std::vector<ChangeFilter>& filters,
                                                         const std::map<std::string, std::uint64_t>& starts,
                                                         Delivery delivery, Millis timeout) {
  auto pending = std::make_shared<Pending>();
  {
    std::lock_guard<std::mutex> lock(mu_);
    if (dead_) deathError_->raise();
    auto w = std::make_shared<Watch>();
    w->watchId = watchId;
    w->filters = filters;
    w->delivery = delivery;
    w->firstStarts = starts;
    watches_[watchId] = w;
    pending_[watchId] = pending;
    // Sent now if a stream is open; otherwise the next open sends it.
    if (stream_) write(createRequest(*w));
  }
  std::unique_lock<std::mutex> lock(mu_);
  if (!cv_.wait_for(lock, timeout, [&] { return pending->done; })) {
    pending_.erase(watchId);
    watches_.erase(watchId);
    if (!connected_) {
      throw UnavailableError("server " + server_.endpoint + " unreachable: the watch was not created within " +
                             std::to_string(timeout.count()) + " ms");
    }
    // The server looks hung: the stream is opened again and the other watches resume.
    if (context_) context_->TryCancel();
    throw DeadlineExceededError(server_.endpoint + " did not confirm watch " + std::to_string(watchId) + " within " +
                                std::to_string(timeout.count()) +
                                " ms: the server looks hung, so the watch stream was ended; it opens again by "
                                "itself and its other watches resume");
  }
  if (pending->error) {
    watches_.erase(watchId);
    pending->error->raise();
  }
  return pending->revisions;
}

void WatchStream::cancel(std::uint32_t watchId) {
  std::lock_guard<std::mutex> lock(mu_);
  watches_.erase(watchId);
  if (stream_) {
    v1::WatchRequest request;
    request.mutable_cancel()->set_watch_id(watchId);
    write(request);
  }
}

void WatchStream::close() {
  {
    std::lock_guard<std::mutex> lock(mu_);
    if (closed_) return;
    closed_ = true;
    if (context_) context_->TryCancel();
  }
  closing_.set();
  if (thread_.joinable()) thread_.join();
}

// Called with mu_ held.
v1::WatchRequest WatchStream::createRequest(Watch& w) {
  v1::WatchRequest request;
  auto* create = request.mutable_create();
  create->set_watch_id(w.watchId);
  create->set_delivery(static_cast<v1::Delivery>(w.delivery));
  for (const auto& f : w.filters) filterToPb(f, create->add_filters());
  if (!w.base) {
    for (const auto& kv : w.firstStarts) (*create->mutable_start_revisions())[kv.first] = kv.second;
    return request;
  }
  std::map<std::string, std::uint64_t> base;
  for (const auto& sa : w.sas) {
    const std::uint64_t from = std::max((*w.base)[sa], seen_[sa]) + 1;
    (*create->mutable_start_revisions())[sa] = from;
    // What is sent is where the watch now is: a later resume never goes back before it.
    base[sa] = from - 1;
  }
  w.base = std::move(base);
  create->set_history_id(historyId_);
  return request;
}

// Called with mu_ held (so writes never overlap: gRPC allows one writer).
bool WatchStream::write(const v1::WatchRequest& request) { return stream_ && stream_->Write(request); }

// Called with mu_ held.
void WatchStream::resolve(std::uint32_t watchId, std::map<std::string, std::uint64_t> revisions,
                          std::shared_ptr<CastError> error) {
  auto it = pending_.find(watchId);
  if (it == pending_.end()) return;
  it->second->done = true;
  it->second->revisions = std::move(revisions);
  it->second->error = std::move(error);
  pending_.erase(it);
  cv_.notify_all();
}

void WatchStream::run() {
  Backoff backoff;
  while (true) {
    std::shared_ptr<grpc::ClientReaderWriter<v1::WatchRequest, v1::WatchResponse>> stream;
    std::shared_ptr<grpc::ClientContext> context;
    // Asking for a session may take a moment (its server is asked where its
    // shared memory is): before the context exists, so close() is not held up.
    {
      std::unique_ptr<ReadCall> read = server_.shared ? server_.shared->read() : nullptr;
      std::lock_guard<std::mutex> lock(framesMu_);
      read_ = std::move(read);
    }
    // The events on the session's socket, when there is one and a queue to hand them to.
    const std::shared_ptr<ClientSession> socketSession = read_ && socket_.now ? read_->session() : nullptr;
    {
      std::lock_guard<std::mutex> lock(mu_);
      if (closed_) break;
      context_ = context = std::make_shared<grpc::ClientContext>();
      authorize(*context, *tokens_);
      if (read_) context->AddMetadata(kSharedMemoryMetadata, read_->metadata());
      if (socketSession) context->AddMetadata(kWatchEventsMetadata, kWatchEventsOnSocket);
    }
    if (socketSession) {
      const ReadCall* call = read_.get();
      {
        std::lock_guard<std::mutex> lock(brokenMu_);
        broken_.clear();
      }
      onSocket_ = call;
      // Before the call opens: a frame may come before the call's first message.
      socketSession->receiveEvents(
          call->number(),
          EventsReceiver{[this, call](const char* data, std::size_t size) { socketBatch(call, data, size); },
                         [this, call](const std::string& why) {
                           breakCall(call, "the socket carrying the watch's events ended: " + why);
                         },
                         socket_.room, socket_.attach});
    }
    // Opening may wait for the connection: not under mu_, so that close()
    // can cancel it.
    stream = server_.wm->Watch(context.get());
    {
      std::lock_guard<std::mutex> lock(mu_);
      stream_ = stream;
      for (auto& kv : watches_) write(createRequest(*kv.second));
    }
    v1::WatchResponse response;
    bool upgrade = false;  // opened without a session, and one is open now: open again with it
    std::shared_ptr<CastError> unreadable;
    while (stream->Read(&response)) {
      if (!connected_) {
        connected_ = true;
        backoff.reset();
      }
      // Cheap while there is none to be had (the link tries again only every
      // few seconds), so a stream opened while its server was away (or
      // restarting) moves to shared memory as soon as there is a session.
      upgrade = !read_ && server_.shared && server_.shared->session();
      try {
        handle(response);
      } catch (const CastError& e) {
        // An event whose shared memory could not be read: read the stream
        // again, from the event after the last one delivered.
        unreadable = std::make_shared<UnavailableError>("an event could not be read: " + e.message());
      }
      if (upgrade || unreadable) {
        context->TryCancel();
        while (stream->Read(&response)) {
        }
        break;
      }
    }
    const grpc::Status status = stream->Finish();
    connected_ = false;
    // The call is over: no frame of it is taken from here on (its watches
    // resume after the last event queued), then say what it received (the
    // server takes back the rest), and see whether the session ended with it.
    std::unique_ptr<ReadCall> ended;
    {
      std::lock_guard<std::mutex> lock(framesMu_);  // a batch being queued is finished first
      onSocket_ = nullptr;
      ended = std::move(read_);
    }
    if (socketSession) socketSession->stopEvents(ended->number());
    if (ended) ended->end(false);
    ended.reset();
    if (server_.shared) server_.shared->check();
    std::string broken;
    if (socketSession) {
      std::lock_guard<std::mutex> lock(brokenMu_);
      broken.swap(broken_);
    }
    if (!broken.empty() && !unreadable) unreadable = std::make_shared<UnavailableError>(broken);
    {
      std::lock_guard<std::mutex> lock(mu_);
      stream_.reset();
      if (closed_) break;
    }
    if (upgrade && !unreadable) continue;
    std::shared_ptr<CastError> error =
        unreadable ? unreadable
        : status.ok()
            ? std::make_shared<UnavailableError>("the watch stream to " + server_.endpoint + " ended")
            : errorForStatus(status, errorTrailer(context->GetServerTrailingMetadata()));
    if (!transient(error->code())) {
      fail(error);
      return;
    }
    log_.warning("watch stream to " + server_.endpoint + " broke (" + error->message() + "); reconnecting");
    if (closing_.wait(backoff.next())) break;
  }
  // Closed: creates still waiting learn why.
  std::lock_guard<std::mutex> lock(mu_);
  auto closedError = std::make_shared<CastError>("the component closed its connection", "CANCELLED");
  while (!pending_.empty()) resolve(pending_.begin()->first, {}, closedError);
}

void WatchStream::handle(const v1::WatchResponse& response) {
  // Events first: a created/failed in the same message refers to a watch
  // that has not matched anything yet.
  for (const auto& event : response.events()) {
    std::vector<std::uint32_t> ids(event.watch_ids().begin(), event.watch_ids().end());
    EventRecord record = eventFromPb(event, read_.get());
    const std::string sa = record.address.subarchitecture;
    const std::uint64_t revision = record.revision;
    sink_(std::move(record), ids);
    std::lock_guard<std::mutex> lock(mu_);
    // The server moves every watch of an SA on one stream past the events it
    // sends, so each watch has seen at least this far.
    if (revision > seen_[sa]) seen_[sa] = revision;
  }
  std::shared_ptr<CastError> resumeRefused;
  {
    std::lock_guard<std::mutex> lock(mu_);
    if (response.has_created()) {
      const auto& created = response.created();
      if (!created.history_id().empty()) historyId_ = created.history_id();
      std::map<std::string, std::uint64_t> revisions(created.revisions().begin(), created.revisions().end());
      auto it = watches_.find(created.watch_id());
      if (it != watches_.end() && !it->second->base) {
        Watch& w = *it->second;
        const bool coversAll = std::any_of(w.filters.begin(), w.filters.end(),
                                           [](const ChangeFilter& f) { return f.subarchitecture.empty(); });
        std::map<std::string, std::uint64_t> base;
        for (const auto& [sa, revision] : revisions) {
          const bool mine = coversAll || std::any_of(w.filters.begin(), w.filters.end(),
                                                     [&](const ChangeFilter& f) { return f.subarchitecture == sa; });
          if (!mine) continue;
          w.sas.push_back(sa);
          auto start = w.firstStarts.find(sa);
          base[sa] = (start == w.firstStarts.end() ? revision + 1 : start->second) - 1;
        }
        w.base = std::move(base);
      }
      resolve(created.watch_id(), std::move(revisions), nullptr);
    }
    if (response.has_failed()) {
      const auto& failed = response.failed();
      auto error = errorForCode(failed.code(), failed.message());
      if (pending_.count(failed.watch_id())) {
        resolve(failed.watch_id(), {}, error);
      } else if (watches_.erase(failed.watch_id()) > 0) {
        // A resume refused after a reconnect: the history no longer covers
        // it (or the server lost it): the component must resynchronise.
        if (error->code() != "OUT_OF_RANGE") {
          error = std::make_shared<HistoryExpiredError>("watch " + std::to_string(failed.watch_id()) +
                                                        " could not resume: " + failed.message());
        }
        resumeRefused = error;
      }
    }
  }
  if (resumeRefused) onError_(resumeRefused);
}

void WatchStream::socketBatch(const ReadCall* call, const char* data, std::size_t size) {
  std::lock_guard<std::mutex> frames(framesMu_);
  if (call != read_.get()) return;  // the call ended: its watches resume after what was queued
  {
    std::lock_guard<std::mutex> lock(brokenMu_);
    if (!broken_.empty()) return;  // ending: the rest comes again on the next call
  }
  v1::WatchResponse response;
  if (size > static_cast<std::size_t>(INT32_MAX) || !response.ParseFromArray(data, static_cast<int>(size))) {
    breakCall(call, "an EVENTS frame of " + std::to_string(size) + " bytes is not a cast.v1.WatchResponse");
    return;
  }
  try {
    for (const auto& event : response.events()) {
      std::vector<std::uint32_t> ids(event.watch_ids().begin(), event.watch_ids().end());
      EventRecord record = eventFromPb(event, read_.get());
      const std::string sa = record.address.subarchitecture;
      const std::uint64_t revision = record.revision;
      socket_.now(std::move(record), ids);
      std::lock_guard<std::mutex> lock(mu_);
      if (revision > seen_[sa]) seen_[sa] = revision;
    }
  } catch (const CastError& e) {
    // A value that could not be claimed: the call is read again from the event after the last one queued.
    breakCall(call, "an event could not be read: " + e.message());
  }
}

// Takes no lock the session's reader holds while it queues a batch: the
// session may end on that thread, or on one that holds its sending lock.
void WatchStream::breakCall(const ReadCall* call, const std::string& why) {
  if (onSocket_.load() != call) return;
  {
    std::lock_guard<std::mutex> lock(brokenMu_);
    if (!broken_.empty()) return;
    broken_ = why;
  }
  std::lock_guard<std::mutex> lock(mu_);
  if (context_) context_->TryCancel();
}

void WatchStream::fail(const std::shared_ptr<CastError>& error) {
  {
    std::lock_guard<std::mutex> lock(mu_);
    dead_ = true;
    deathError_ = error;
    watches_.clear();
    while (!pending_.empty()) resolve(pending_.begin()->first, {}, error);
  }
  onError_(error);
}

}  // namespace cast::detail
