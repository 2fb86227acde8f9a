// One session with a server's shared memory (shm_session.h). Mirrors the
// Python client's client/shm_session.py.
#include "shm_session.h"

#include <fcntl.h>
#include <poll.h>
#include <sys/mman.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstring>
#include <iterator>
#include <system_error>

#include "cast/errors.h"
#include "cast/log.h"

namespace cast::detail {

namespace {

constexpr std::size_t kPage = 4096;
// How long a claim waits for the SEGMENT frame sent before the message naming
// it: it is in the socket already, or comes at once.
constexpr std::chrono::milliseconds kSegmentWait{5000};
// How long a frame may wait for room in the socket: the server reads it at
// once unless it is stuck.
constexpr std::chrono::milliseconds kSendWait{5000};
// A long call reports what it received this often, so the server forgets the rest.
constexpr std::uint64_t kReceivedEvery = 64;
// How long the reader thread waits on the socket at most, so that it looks at
// the writes' deadlines; and, while the queue its events go to is full, how
// often it looks for room.
constexpr std::chrono::milliseconds kReaderTurn{100};
constexpr std::chrono::milliseconds kRoomTurn{10};

std::atomic<std::uint64_t> eventFrames{0};
std::atomic<std::uint64_t> readerThreads{0};

const Logger& log() {
  static const Logger logger("cast.client.shm");
  return logger;
}

// A value lent to this client: its bytes in a mapped segment (kept mapped
// while this lives), given back when it goes.
class Lease final : public LentBytes {
 public:
  Lease(std::weak_ptr<ClientSession> session, std::shared_ptr<const Mapping> segment, std::uint64_t valueId,
        const char* data, std::size_t size)
      : LentBytes(data, size), session_(std::move(session)), segment_(std::move(segment)), valueId_(valueId) {}
  ~Lease() override {
    // A session that is gone gave everything back by ending.
    if (auto session = session_.lock()) session->giveBack(valueId_);
  }

 private:
  std::weak_ptr<ClientSession> session_;
  std::shared_ptr<const Mapping> segment_;
  std::uint64_t valueId_;
};

}  // namespace

// ------------------------------------------------------------------ helpers

Mapping::~Mapping() {
  if (address_ != nullptr && address_ != MAP_FAILED) ::munmap(address_, size_);
}

std::size_t roundUpToPages(std::size_t size) { return size == 0 ? kPage : (size + kPage - 1) / kPage * kPage; }

Extents::Extents(std::size_t size) : size_(size) {
  if (size > 0) free_[0] = size;
}

std::optional<std::size_t> Extents::take(std::size_t size) {
  for (auto it = free_.begin(); it != free_.end(); ++it) {
    if (it->second < size) continue;
    const std::size_t offset = it->first;
    const std::size_t rest = it->second - size;
    free_.erase(it);
    if (rest > 0) free_[offset + size] = rest;
    used_ += size;
    return offset;
  }
  return std::nullopt;
}

void Extents::give(std::size_t offset, std::size_t size) {
  used_ -= size;
  auto next = free_.lower_bound(offset);
  if (next != free_.begin()) {
    auto before = std::prev(next);
    if (before->first + before->second == offset) {
      offset = before->first;
      size += before->second;
      free_.erase(before);
    }
  }
  if (next != free_.end() && offset + size == next->first) {
    size += next->second;
    free_.erase(next);
  }
  free_[offset] = size;
}

// ------------------------------------------------------------------ ReadCall

ReadCall::ReadCall(std::shared_ptr<ClientSession> session, std::uint64_t number)
    : session_(std::move(session)), number_(number), metadata_(shm::hex(session_->id()) + "/" + std::to_string(number)) {}

ReadCall::~ReadCall() {
  try {
    end(false);
  } catch (...) {  // a destructor must not throw; sending never does, this is for the allocator
  }
}

std::shared_ptr<const LentBytes> ReadCall::claim(const v1::SharedValue& ref) {
  ++count_;
  if (count_ % kReceivedEvery == 0) session_->send(shm::received(number_, count_, false));
  return session_->claim(ref);
}

void ReadCall::end(bool answered) {
  if (ended_) return;
  ended_ = true;
  if (count_ > 0 || !answered) session_->send(shm::received(number_, count_, true));
}

// ------------------------------------------------------------------ ClientSession

ClientSession::ClientSession(int socket, const shm::Welcome& welcome, int stagingFd, std::string endpoint)
    : endpoint_(std::move(endpoint)),
      socket_(socket),
      id_(welcome.session),
      idHex_(shm::hex(welcome.session)),
      serverId_(shm::hex(welcome.serverId)),
      threshold_(welcome.threshold),
      window_(welcome.window),
      stagingSize_(static_cast<std::size_t>(welcome.staging)),
      regions_(static_cast<std::size_t>(welcome.staging)) {
  void* address = stagingSize_ == 0 ? MAP_FAILED
                                    : ::mmap(nullptr, stagingSize_, PROT_READ | PROT_WRITE, MAP_SHARED, stagingFd, 0);
  const int error = errno;
  ::close(stagingFd);  // the mapping keeps the memory file
  if (address == MAP_FAILED) {
    ::close(socket_);
    throw std::system_error(error, std::generic_category(), "mapping the staging area");
  }
  staging_ = std::make_shared<Mapping>(address, stagingSize_);
  writes_ = std::make_unique<SessionWrites>(*this, endpoint_);
  // From here on the socket is read whenever the session is used, never waited on.
  ::fcntl(socket_, F_SETFL, ::fcntl(socket_, F_GETFL) | O_NONBLOCK);
}

ClientSession::~ClientSession() {
  end("closed");
  {
    std::lock_guard<std::mutex> lock(threadMu_);
    stopped_ = true;
  }
  if (thread_.joinable()) {
    // The reader thread let the last holder go: it ends at its next turn, touching nothing of this.
    if (thread_.get_id() == std::this_thread::get_id()) {
      thread_.detach();
    } else {
      thread_.join();  // it holds no reference between turns, so it is past its last one
    }
  }
  writes_.reset();
  ::close(socket_);
}

std::string ClientSession::why() const {
  std::lock_guard<std::mutex> lock(stateMu_);
  return why_;
}

std::size_t ClientSession::segments() const {
  std::lock_guard<std::mutex> lock(stateMu_);
  return segments_.size();
}

std::size_t ClientSession::quarantined() const {
  std::lock_guard<std::mutex> lock(stateMu_);
  return quarantined_;
}

std::size_t ClientSession::stagingUsed() const {
  std::lock_guard<std::mutex> lock(stateMu_);
  return staging_ ? regions_.used() : 0;
}

std::shared_ptr<const Mapping> ClientSession::stagingArea() const {
  std::lock_guard<std::mutex> lock(stateMu_);
  return staging_;
}

// -------------------------------------------------------------------- writes

std::optional<Staged> ClientSession::stage(std::string_view data) {
  return stage(data.size(), [&](std::uint8_t* out) { std::memcpy(out, data.data(), data.size()); });
}

std::optional<Staged> ClientSession::stage(std::size_t size, const std::function<void(std::uint8_t*)>& fill) {
  poll();  // a session the server ended (it restarted) is noticed before a write names it
  Staged staged;
  staged.size = size;
  staged.taken = roundUpToPages(size);
  std::shared_ptr<Mapping> staging;
  {
    std::lock_guard<std::mutex> lock(stateMu_);
    if (dead_ || !staging_) return std::nullopt;
    const auto offset = regions_.take(staged.taken);
    if (!offset) return std::nullopt;
    staged.offset = *offset;
    staging = staging_;  // kept mapped while the copy runs, whatever ends the session meanwhile
  }
  fill(reinterpret_cast<std::uint8_t*>(staging->data()) + staged.offset);
  return staged;
}

std::optional<Reserved> ClientSession::reserve(std::size_t size, std::size_t payload) {
  poll();  // as stage(): a session the server ended is noticed before a loan is placed in it
  // Regions start on a page (Extents hands out whole pages from 0), so the pad
  // is known before the region is: the payload's offset in the region.
  Reserved out;
  out.staged.pad = (kLoanAlignment - payload % kLoanAlignment) % kLoanAlignment;
  out.staged.size = size;
  out.staged.taken = roundUpToPages(out.staged.pad + size);
  std::lock_guard<std::mutex> lock(stateMu_);
  if (dead_ || !staging_) return std::nullopt;
  const auto start = regions_.take(out.staged.taken);
  if (!start) return std::nullopt;
  out.staged.offset = *start + out.staged.pad;
  out.staging = staging_;
  return out;
}

void ClientSession::describe(const Staged& staged, v1::StagedValue* out) const {
  out->set_session(id_);
  out->set_offset(staged.offset);
  out->set_size(staged.size);
}

void ClientSession::unstage(const Staged& staged, bool known) {
  std::lock_guard<std::mutex> lock(stateMu_);
  if (!staging_) return;  // the session ended: nothing of it is used again
  if (known) {
    regions_.give(staged.offset - staged.pad, staged.taken);  // the whole region, a loan's pad included
  } else {
    quarantined_ += staged.taken;
  }
}

// --------------------------------------------------------------------- reads

std::unique_ptr<ReadCall> ClientSession::newCall() {
  poll();  // RETIRE and the end, read now and then even by a client that only reads
  std::uint64_t number;
  {
    std::lock_guard<std::mutex> lock(stateMu_);
    number = ++calls_;
  }
  return std::make_unique<ReadCall>(shared_from_this(), number);
}

std::shared_ptr<const LentBytes> ClientSession::claim(const v1::SharedValue& ref) {
  std::shared_ptr<const Mapping> segment;
  {
    std::lock_guard<std::mutex> lock(stateMu_);
    auto it = segments_.find(ref.segment());
    if (it != segments_.end()) segment = it->second;
  }
  if (!segment && polling_.load() == std::this_thread::get_id()) {
    // An event read from the socket on this thread: its segment came before it, or never will.
    giveBack(ref.value_id());
    throw UnavailableError("shared-memory segment " + std::to_string(ref.segment()) + " of the server at " +
                           endpoint_ + " did not arrive before the event naming it: read again");
  }
  if (!segment) {
    // Sent before the message naming it: in the socket already, or coming at once.
    const auto until = std::chrono::steady_clock::now() + kSegmentWait;
    for (;;) {
      const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(until - std::chrono::steady_clock::now());
      poll(std::max(std::chrono::milliseconds(1), std::min(std::chrono::milliseconds(100), left)));
      {
        std::lock_guard<std::mutex> lock(stateMu_);
        auto it = segments_.find(ref.segment());
        if (it != segments_.end()) segment = it->second;
      }
      if (segment) break;
      if (dead_ || std::chrono::steady_clock::now() >= until) {
        giveBack(ref.value_id());
        const std::string reason = dead_ ? why() : "within 5 s";
        throw UnavailableError("shared-memory segment " + std::to_string(ref.segment()) + " of the server at " +
                               endpoint_ + " did not arrive (" + reason + "): read again");
      }
    }
  }
  if (ref.offset() > segment->size() || ref.size() > segment->size() - ref.offset()) {
    giveBack(ref.value_id());
    throw UnavailableError("the server at " + endpoint_ + " named bytes " + std::to_string(ref.offset()) + ".." +
                           std::to_string(ref.offset() + ref.size()) + " of shared-memory segment " +
                           std::to_string(ref.segment()) + ", which has " + std::to_string(segment->size()) +
                           ": read again");
  }
  const char* data = segment->data() + ref.offset();
  return std::make_shared<Lease>(weak_from_this(), std::move(segment), ref.value_id(), data,
                                 static_cast<std::size_t>(ref.size()));
}

void ClientSession::giveBack(std::uint64_t valueId) {
  {
    std::lock_guard<std::mutex> lock(unsentMu_);
    unsent_.push_back(valueId);
  }
  sendQueued();
}

// -------------------------------------------------------------------- events

void ClientSession::receiveEvents(std::uint64_t call, EventsReceiver receiver) {
  {
    std::lock_guard<std::mutex> lock(endMu_);
    enders_[call] = receiver.ended;
  }
  {
    std::lock_guard<std::mutex> lock(eventsMu_);
    receivers_[call] = receiver;
  }
  if (receiver.attach) {
    receiver.attach(weak_from_this());
  } else {
    startReader();
  }
}

void ClientSession::stopEvents(std::uint64_t call) {
  {
    std::lock_guard<std::mutex> lock(eventsMu_);
    receivers_.erase(call);
  }
  std::lock_guard<std::mutex> lock(endMu_);
  enders_.erase(call);
}

std::uint64_t ClientSession::eventFramesHandled() { return eventFrames.load(std::memory_order_relaxed); }

std::uint64_t ClientSession::readersStarted() { return readerThreads.load(std::memory_order_relaxed); }

void ClientSession::events(const std::string& body) {
  const std::uint64_t call = shm::parseEventsCall(body);
  std::lock_guard<std::mutex> lock(eventsMu_);
  auto it = receivers_.find(call);
  if (it == receivers_.end()) return;  // its call ended: its watches resume after what was delivered
  eventFrames.fetch_add(1, std::memory_order_relaxed);
  it->second.batch(body.data() + 8, body.size() - 8);
}

// ------------------------------------------------------------- reader thread

void ClientSession::startReader() {
  std::lock_guard<std::mutex> lock(threadMu_);
  if (thread_.joinable() || stopped_ || dead_) return;
  thread_ = std::thread([weak = weak_from_this()] { readLoop(weak); });
  readerThreads.fetch_add(1, std::memory_order_relaxed);
}

void ClientSession::readLoop(const std::weak_ptr<ClientSession>& weak) {
  for (;;) {
    // Held for one turn only, so that the session goes when its last user lets it go.
    std::shared_ptr<ClientSession> self = weak.lock();
    if (!self || self->dead_) return;
    {
      std::lock_guard<std::mutex> lock(self->threadMu_);
      if (self->stopped_) return;
    }
    self->readOnce();
  }
}

void ClientSession::readOnce() {
  const std::chrono::milliseconds wait = std::min(kReaderTurn, writes_->expire());
  if (dead_) return;
  if (writes_->outstanding() == 0) {
    std::function<bool(std::chrono::milliseconds)> room;
    {
      std::lock_guard<std::mutex> lock(eventsMu_);
      for (const auto& kv : receivers_) {
        if (kv.second.room) room = kv.second.room;  // one component's queue: any receiver's says
      }
    }
    // Full: the socket is not read (no write waits for its reply), so the server holds what comes.
    if (room && !room(std::min(wait, kRoomTurn))) return;
  }
  poll(std::max(std::chrono::milliseconds(1), wait));
}

// -------------------------------------------------------------------- frames

void ClientSession::send(const std::string& frame) {
  {
    std::lock_guard<std::mutex> lock(sendMu_);
    flushLocked();
    writeLocked(frame);
  }
  sendQueued();
}

// Sends what was given back while another thread was sending, if no one else is.
void ClientSession::sendQueued() {
  for (;;) {
    {
      std::lock_guard<std::mutex> lock(unsentMu_);
      if (unsent_.empty()) return;
    }
    if (!sendMu_.try_lock()) return;  // its holder sends them when it lets go
    flushLocked();
    sendMu_.unlock();
  }
}

void ClientSession::flushLocked() {
  std::vector<std::uint64_t> ids;
  {
    std::lock_guard<std::mutex> lock(unsentMu_);
    ids.swap(unsent_);
  }
  for (std::size_t at = 0; at < ids.size(); at += shm::kMaxReleaseIds) {
    const auto end = std::min(ids.size(), at + shm::kMaxReleaseIds);
    writeLocked(shm::release(std::vector<std::uint64_t>(ids.begin() + static_cast<std::ptrdiff_t>(at),
                                                        ids.begin() + static_cast<std::ptrdiff_t>(end))));
  }
}

bool ClientSession::writeLocked(const std::string& frame) {
  if (dead_) return false;
  std::size_t at = 0;
  const auto until = std::chrono::steady_clock::now() + kSendWait;
  while (at < frame.size()) {
    const ssize_t n = ::send(socket_, frame.data() + at, frame.size() - at, MSG_NOSIGNAL | MSG_DONTWAIT);
    if (n >= 0) {
      at += static_cast<std::size_t>(n);
      continue;
    }
    if (errno == EINTR) continue;
    if (errno != EAGAIN && errno != EWOULDBLOCK) {
      end(std::string("write failed: ") + std::strerror(errno));
      return false;
    }
    if (std::chrono::steady_clock::now() >= until) {
      end("the server has not read its socket for 5 s");
      return false;
    }
    pollfd p{socket_, POLLOUT, 0};
    ::poll(&p, 1, 100);
  }
  return true;
}

bool ClientSession::poll(std::chrono::milliseconds wait) {
  if (dead_) return true;
  std::unique_lock<std::timed_mutex> lock(readMu_, std::defer_lock);
  if (wait.count() > 0 ? !lock.try_lock_for(wait) : !lock.try_lock()) return false;  // another reader handles what came
  reading_.store(true);
  if (wait.count() > 0) {
    pollfd p{socket_, POLLIN, 0};
    ::poll(&p, 1, static_cast<int>(wait.count()));
  }
  readAvailable();
  reading_.store(false);
  lock.unlock();
  readerLeft();
  return true;
}

int ClientSession::sourceFd() const { return dead_ ? -1 : socket_; }

bool ClientSession::pump() { return poll(); }

bool ClientSession::readUntil(const std::function<bool()>& done, std::chrono::milliseconds wait) {
  if (dead_) return true;
  std::unique_lock<std::timed_mutex> lock(readMu_, std::try_to_lock);
  if (!lock) return false;
  reading_.store(true);
  const auto until = std::chrono::steady_clock::now() + wait;
  while (!dead_ && !done()) {
    const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(until - std::chrono::steady_clock::now());
    if (left.count() <= 0) break;
    pollfd p{socket_, POLLIN, 0};
    if (::poll(&p, 1, static_cast<int>(left.count())) <= 0) continue;  // its time is up, or a signal: look again
    readAvailable();
  }
  reading_.store(false);
  lock.unlock();
  readerLeft();
  return true;
}

void ClientSession::readerLeft() {
  if (writes_) writes_->readerLeft();
}

void ClientSession::readAvailable() {
  polling_.store(std::this_thread::get_id());
  struct Done {
    std::atomic<std::thread::id>& polling;
    ~Done() { polling.store(std::thread::id()); }
  } done{polling_};
  shm::Inbox& inbox = inbox_;
  while (!dead_) {
    std::optional<std::vector<int>> fds;
    try {
      socketReads_.fetch_add(1, std::memory_order_relaxed);
      fds = inbox.receive(socket_);
    } catch (const std::exception& e) {
      end(std::string("read failed: ") + e.what());
      break;
    }
    if (!fds) break;  // nothing more now
    if (inbox.size() == 0) {
      for (int fd : *fds) ::close(fd);
      end("the server closed the session");
      break;
    }
    const bool drained = !inbox.full();  // the socket held no more: no second read to learn it
    std::vector<shm::Frame> frames;
    try {
      frames = reader_.feed(inbox.data(), inbox.size(), std::move(*fds));
    } catch (const shm::ProtocolError& e) {
      end(e.what());
      break;
    }
    for (auto& frame : frames) handle(frame);
    if (drained) break;
  }
}

void ClientSession::handle(shm::Frame& frame) {
  try {
    if (frame.kind == shm::kSegment) {
      const auto [segmentId, size] = shm::parseSegment(frame.body);
      void* address = size == 0 ? MAP_FAILED
                                : ::mmap(nullptr, static_cast<std::size_t>(size), PROT_READ, MAP_SHARED, frame.fd, 0);
      const int error = errno;
      ::close(frame.fd);  // the mapping keeps the memory file
      frame.fd = -1;
      if (address == MAP_FAILED) {
        end("segment " + std::to_string(segmentId) + " could not be mapped: " + std::strerror(error));
        return;
      }
      auto mapping = std::make_shared<const Mapping>(address, static_cast<std::size_t>(size));
      std::lock_guard<std::mutex> lock(stateMu_);
      if (!dead_) segments_[segmentId] = std::move(mapping);
    } else if (frame.kind == shm::kRetire) {
      const std::uint32_t segmentId = shm::parseRetire(frame.body);
      std::shared_ptr<const Mapping> gone;  // unmapped outside the lock, once no value of it is held
      std::lock_guard<std::mutex> lock(stateMu_);
      auto it = segments_.find(segmentId);
      if (it != segments_.end()) {
        gone = std::move(it->second);
        segments_.erase(it);
      }
    } else if (frame.kind == shm::kReplies) {
      writes_->replies(frame.body);
    } else if (frame.kind == shm::kEvents) {
      events(frame.body);
    } else if (frame.kind == shm::kRefused) {
      end("the server ended it: " + frame.body);
    } else if (frame.fd >= 0) {  // a kind this client does not know
      ::close(frame.fd);
      frame.fd = -1;
    }
  } catch (const shm::ProtocolError& e) {
    if (frame.fd >= 0) ::close(frame.fd);
    end(e.what());
  }
}

void ClientSession::end(const std::string& why) {
  std::shared_ptr<Mapping> staging;
  std::map<std::uint32_t, std::shared_ptr<const Mapping>> segments;
  {
    std::lock_guard<std::mutex> lock(stateMu_);
    if (dead_) return;
    dead_ = true;
    why_ = why.empty() ? "closed" : why;
    // Mappings still held by values go when those do (their leases hold them);
    // the staging area stays mapped while a copy into it is under way or a
    // loan lives (each holds it: a loan's buffer is never unmapped under it).
    staging.swap(staging_);
    segments.swap(segments_);
  }
  // Wakes a reader blocked on the socket; closed by the destructor, so that
  // no other thread ever uses a descriptor number that was closed.
  ::shutdown(socket_, SHUT_RDWR);
  if (why != "closed") log().debug("shared-memory session with " + endpoint_ + " ended: " + why);
  if (writes_) writes_->ended(why.empty() ? "closed" : why);
  {
    // The watches whose events came here end their calls, and resume on new ones.
    std::lock_guard<std::mutex> lock(endMu_);
    for (auto& kv : enders_) {
      if (kv.second) kv.second(why.empty() ? "closed" : why);
    }
    enders_.clear();
  }
  // Descriptors no frame claimed are closed with the reader, by the destructor.
}

void ClientSession::close() { end("closed"); }

void ClientSession::abandon(const std::string& why) { end(why); }

}  // namespace cast::detail
