// Write-stream requests on the shared-memory session's socket
// (socket_writes.h).
#include "socket_writes.h"

#include <algorithm>
#include <utility>
#include <vector>

#include "durations.h"
#include "shm_session.h"
#include "shm_wire.h"

namespace cast::detail {

SessionWrites::SessionWrites(ClientSession& session, std::string endpoint)
    : session_(session), endpoint_(std::move(endpoint)) {}

bool SessionWrites::send(v1::WriteRequest& request, ReplyHandler& onReply,
                         std::optional<std::chrono::milliseconds> timeout, bool waited) {
  v1::WriteRequests message;
  {
    std::lock_guard<std::mutex> lock(mu_);
    if (ended_) return false;
    request.set_id(nextId_++);
    Pending p;
    p.onReply = std::move(onReply);
    if (timeout) {
      p.deadline = Clock::now() + *timeout;
      p.timeout = *timeout;
    }
    pending_.emplace(request.id(), std::move(p));
  }
  sent_.fetch_add(1, std::memory_order_relaxed);
  if (!waited) session_.startReader();
  message.add_requests()->Swap(&request);
  // A frame that cannot be sent ends the session, which fails this request with the others.
  const std::string frame = shm::writes(message.SerializeAsString());
  sentBytes_.fetch_add(frame.size(), std::memory_order_relaxed);
  session_.send(frame);
  return true;
}

void SessionWrites::await(const std::function<bool()>& answered) {
  // How long one read waits before its reader looks at the deadlines again.
  constexpr std::chrono::milliseconds kSlice{50};
  while (!answered() && !session_.dead()) {
    if (!session_.readUntil(answered, kSlice)) {
      std::unique_lock<std::mutex> lock(mu_);
      followers_.fetch_add(1);  // before it looks who reads: a reader leaving now sees it and wakes it
      changed_.wait_for(lock, kSlice, [&] { return answered() || ended_ || !session_.reading(); });
      followers_.fetch_sub(1);
    }
    expire();
  }
}

void SessionWrites::readerLeft() {
  if (followers_.load() == 0) return;
  std::lock_guard<std::mutex> lock(mu_);
  changed_.notify_all();
}

void SessionWrites::drain(std::chrono::milliseconds timeout) {
  std::unique_lock<std::mutex> lock(mu_);
  changed_.wait_for(lock, timeout, [this] { return pending_.empty(); });
}

std::size_t SessionWrites::outstanding() {
  std::lock_guard<std::mutex> lock(mu_);
  return pending_.size();
}

void SessionWrites::replies(const std::string& body) {
  v1::WriteReplies message;
  if (!message.ParseFromString(body)) throw shm::ProtocolError("a REPLIES frame is not a cast.v1.WriteReplies");
  std::vector<std::pair<ReplyHandler, const v1::WriteReply*>> answered;
  {
    std::lock_guard<std::mutex> lock(mu_);
    for (const auto& reply : message.replies()) {
      auto it = pending_.find(reply.id());
      if (it == pending_.end()) continue;  // its deadline passed: its sender has the error
      answered.emplace_back(std::move(it->second.onReply), &reply);
      pending_.erase(it);
    }
    if (pending_.empty()) changed_.notify_all();
  }
  for (auto& [handler, reply] : answered) handler(reply, nullptr);
  if (followers_.load() > 0) {
    std::lock_guard<std::mutex> lock(mu_);
    changed_.notify_all();  // a waiter whose reply this was (its handler has run)
  }
}

void SessionWrites::ended(const std::string& why) {
  std::map<std::uint64_t, Pending> left;
  {
    std::lock_guard<std::mutex> lock(mu_);
    ended_ = true;
    left.swap(pending_);
    changed_.notify_all();
  }
  if (left.empty()) return;
  const auto error = std::make_shared<UnavailableError>(
      "the shared-memory session with " + endpoint_ + " ended (" + why +
      "): this write may or may not have been applied; the client reconnects by itself, retry the call later");
  for (auto& kv : left) kv.second.onReply(nullptr, error);
}

std::chrono::milliseconds SessionWrites::expire() {
  // With nothing due, the reader thread still looks this often.
  std::chrono::milliseconds wait{100};
  std::vector<std::pair<ReplyHandler, std::shared_ptr<CastError>>> expired;
  {
    std::lock_guard<std::mutex> lock(mu_);
    if (ended_) return wait;
    const auto now = Clock::now();
    for (auto it = pending_.begin(); it != pending_.end();) {
      const Pending& p = it->second;
      if (!p.deadline || *p.deadline > now) {
        if (p.deadline) {
          wait = std::min(wait, std::chrono::duration_cast<std::chrono::milliseconds>(*p.deadline - now) +
                                    std::chrono::milliseconds(1));
        }
        ++it;
        continue;
      }
      expired.emplace_back(std::move(it->second.onReply),
                           std::make_shared<DeadlineExceededError>(
                               "no reply from " + endpoint_ + " on the shared-memory session within " +
                               secondsText(p.timeout) + ": the write may or may not have been applied; the session "
                               "was ended and the next write opens a new one"));
      it = pending_.erase(it);
    }
    if (!expired.empty() && pending_.empty()) changed_.notify_all();
  }
  if (expired.empty()) return wait;
  for (auto& [handler, error] : expired) handler(nullptr, error);
  // A server that answers nothing in that time is hung: end the session, failing the others.
  session_.abandon(endpoint_ + " answered no write on the shared-memory session within its deadline");
  return wait;
}

}  // namespace cast::detail
