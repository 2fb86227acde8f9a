// Whether there is a shared-memory session with a server (shm.h). Mirrors
// the Python client's client/shm.py.
#include "shm.h"

#include <poll.h>
#include <sys/socket.h>
#include <sys/un.h>
#include <unistd.h>

#include <algorithm>
#include <cctype>
#include <cerrno>
#include <cstddef>
#include <cstdlib>
#include <cstring>
#include <system_error>

#include "cast/errors.h"
#include "conversions.h"
#include "loan_state.h"
#include "shm_wire.h"

namespace cast::detail {

namespace {

using Clock = std::chrono::steady_clock;

// How long after a failure the link tries again; when the server is elsewhere
// or offers none, longer (a restart of it may change that).
constexpr std::chrono::seconds kRetry{5};
constexpr std::chrono::seconds kRetryElsewhere{60};
constexpr std::chrono::milliseconds kRenewDrain{30000};  // a renewed token: how long the old session's writes may take

// Closes a descriptor when it goes, unless taken.
class Fd {
 public:
  explicit Fd(int fd) : fd_(fd) {}
  ~Fd() {
    if (fd_ >= 0) ::close(fd_);
  }
  Fd(const Fd&) = delete;
  Fd& operator=(const Fd&) = delete;
  int get() const { return fd_; }
  int take() {
    const int fd = fd_;
    fd_ = -1;
    return fd;
  }

 private:
  int fd_;
};

std::string errnoText(int error) { return std::strerror(error); }

// Writes all of `frame` (a blocking socket with a send timeout).
void sendAll(int fd, const std::string& frame) {
  std::size_t at = 0;
  while (at < frame.size()) {
    const ssize_t n = ::send(fd, frame.data() + at, frame.size() - at, MSG_NOSIGNAL);
    if (n < 0) {
      if (errno == EINTR) continue;
      throw NoSession("sending HELLO failed: " + errnoText(errno), false);
    }
    at += static_cast<std::size_t>(n);
  }
}

}  // namespace

bool sharedMemoryTurnedOff() {
  const char* value = std::getenv(kSharedMemoryEnv);
  if (value == nullptr) return false;
  std::string v(value);
  v.erase(std::remove_if(v.begin(), v.end(), [](unsigned char c) { return std::isspace(c); }), v.end());
  std::transform(v.begin(), v.end(), v.begin(), [](unsigned char c) { return static_cast<char>(std::tolower(c)); });
  return v == "off" || v == "0" || v == "false" || v == "no";
}

std::shared_ptr<ClientSession> connectShared(const v1::SharedMemoryInfo& info, const std::string& token,
                                             const std::string& endpoint, std::chrono::milliseconds within) {
  within = std::clamp(within, std::chrono::milliseconds(1), kConnectWait);
  const auto until = Clock::now() + within;
  Fd sock(::socket(AF_UNIX, SOCK_STREAM | SOCK_CLOEXEC, 0));
  if (sock.get() < 0) throw NoSession("no Unix socket: " + errnoText(errno), false);
  // The handshake is bounded: a server that takes the connection but says nothing ends it.
  timeval bound{static_cast<time_t>(within.count() / 1000), static_cast<suseconds_t>(within.count() % 1000 * 1000)};
  ::setsockopt(sock.get(), SOL_SOCKET, SO_RCVTIMEO, &bound, sizeof bound);
  ::setsockopt(sock.get(), SOL_SOCKET, SO_SNDTIMEO, &bound, sizeof bound);

  // The abstract address: a NUL byte, then the name, no terminating NUL; the
  // length covers exactly those bytes.
  sockaddr_un address{};
  address.sun_family = AF_UNIX;
  if (info.socket().empty() || info.socket().size() + 1 > sizeof address.sun_path) {
    throw NoSession("its socket name '" + info.socket() + "' is not one this client can reach", false);
  }
  std::memcpy(address.sun_path + 1, info.socket().data(), info.socket().size());
  const auto length = static_cast<socklen_t>(offsetof(sockaddr_un, sun_path) + 1 + info.socket().size());
  int rc;
  do {
    rc = ::connect(sock.get(), reinterpret_cast<const sockaddr*>(&address), length);
  } while (rc < 0 && errno == EINTR);
  if (rc < 0) {
    const int error = errno;
    if (error == ENOENT || error == ECONNREFUSED) {
      throw NoSession("its socket is not reachable from here (" + errnoText(error) +
                          "): another host or network namespace",
                      true);
    }
    throw NoSession("connecting to its socket failed: " + errnoText(error), false);
  }

  // The peer must run as this process's OS user: else the socket is someone else's.
  ucred peer{};
  socklen_t peerSize = sizeof peer;
  if (::getsockopt(sock.get(), SOL_SOCKET, SO_PEERCRED, &peer, &peerSize) != 0) {
    throw NoSession("its socket's peer credentials cannot be read: " + errnoText(errno), false);
  }
  if (peer.uid != ::geteuid()) {
    throw NoSession("the process behind its socket (" + std::to_string(peer.pid) + ") runs as OS user " +
                        std::to_string(peer.uid) + ", this one as " + std::to_string(::geteuid()),
                    false);
  }

  sendAll(sock.get(), shm::hello(token));
  shm::FrameReader reader;
  std::vector<shm::Frame> frames;
  shm::Inbox inbox;
  while (frames.empty()) {
    const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(until - Clock::now());
    if (left.count() <= 0) {
      throw NoSession("no WELCOME within " + std::to_string(within.count()) + " ms", false);
    }
    pollfd p{sock.get(), POLLIN, 0};
    if (::poll(&p, 1, static_cast<int>(left.count())) <= 0) continue;
    std::optional<std::vector<int>> fds;
    try {
      fds = inbox.receive(sock.get());
    } catch (const std::exception& e) {
      throw NoSession(std::string("reading its answer failed: ") + e.what(), false);
    }
    if (!fds) continue;
    if (inbox.size() == 0) throw NoSession("the server closed the connection after HELLO", false);
    try {
      frames = reader.feed(inbox.data(), inbox.size(), std::move(*fds));
    } catch (const shm::ProtocolError& e) {
      throw NoSession(std::string("its answer broke the protocol: ") + e.what(), false);
    }
  }
  shm::Frame first = std::move(frames.front());
  for (std::size_t i = 1; i < frames.size(); ++i) {
    if (frames[i].fd >= 0) ::close(frames[i].fd);  // nothing may come before WELCOME is taken
  }
  Fd staging(first.fd);
  if (first.kind == shm::kRefused) throw NoSession("refused: " + first.body, false);
  if (first.kind != shm::kWelcome || staging.get() < 0) {
    throw NoSession("answered HELLO with a frame of kind " + std::to_string(first.kind), false);
  }
  shm::Welcome welcome;
  try {
    welcome = shm::parseWelcome(first.body);
  } catch (const shm::ProtocolError& e) {
    throw NoSession(e.what(), false);
  }
  if (shm::hex(welcome.serverId) != info.server_id()) {
    throw NoSession("its socket belongs to another server (id " + shm::hex(welcome.serverId) + ", not " +
                        info.server_id() + ")",
                    false);
  }
  try {
    // Takes the socket and the staging area's descriptor, whatever happens.
    const int fd = staging.take();
    auto session = std::make_shared<ClientSession>(sock.take(), welcome, fd, endpoint);
    session->setReads(info.reads());
    return session;
  } catch (const std::system_error& e) {
    throw NoSession(e.what(), false);
  }
}

// ------------------------------------------------------------------ SharedLink

SharedLink::SharedLink(std::string endpoint, std::shared_ptr<TokenSource> tokens, Describe describe, Logger log)
    : endpoint_(std::move(endpoint)), tokens_(std::move(tokens)), describe_(std::move(describe)), log_(std::move(log)) {}

SharedLink::~SharedLink() { close(); }

std::shared_ptr<ClientSession> SharedLink::session(Within within) {
  const auto started = Clock::now();
  {
    std::lock_guard<std::mutex> lock(mu_);
    if (session_ && !session_->dead()) return session_;
    if (closed_ || forever_ || Clock::now() < retryAt_) return nullptr;
  }
  // One opening at a time; the others wait for its outcome, as long as their
  // call may (past that, bytes: the opening goes on for the next call).
  std::unique_lock<std::timed_mutex> opening(openMu_, std::defer_lock);
  if (within) {
    if (!opening.try_lock_for(*within)) return nullptr;
  } else {
    opening.lock();
  }
  {
    std::lock_guard<std::mutex> lock(mu_);
    if (session_ && !session_->dead()) return session_;
    if (closed_ || forever_ || Clock::now() < retryAt_) return nullptr;
  }
  if (within) {
    within = *within - std::chrono::duration_cast<std::chrono::milliseconds>(Clock::now() - started);
    if (within->count() <= 0) return nullptr;
  }
  std::shared_ptr<ClientSession> fresh = open(nullptr, within);
  std::lock_guard<std::mutex> lock(mu_);
  if (closed_) {
    if (fresh) fresh->close();
    return nullptr;
  }
  session_ = fresh;  // a dead one goes: its mappings go with the values still holding them
  if (fresh) reason_.clear();
  return fresh;
}

void SharedLink::open(const v1::SystemDescription& described) {
  std::lock_guard<std::timed_mutex> opening(openMu_);
  {
    std::lock_guard<std::mutex> lock(mu_);
    if (closed_ || forever_ || (session_ && !session_->dead())) return;
  }
  std::shared_ptr<ClientSession> fresh = open(&described, std::nullopt);
  std::lock_guard<std::mutex> lock(mu_);
  if (closed_) {
    if (fresh) fresh->close();
    return;
  }
  session_ = fresh;
  if (fresh) reason_.clear();
}

std::shared_ptr<ClientSession> SharedLink::open(const v1::SystemDescription* described, Within within) {
  const auto started = Clock::now();
  if (sharedMemoryTurnedOff()) {
    fallback(std::string("turned off by ") + kSharedMemoryEnv + "=" + std::getenv(kSharedMemoryEnv),
             kRetryElsewhere, true);
    return nullptr;
  }
  v1::SharedMemoryInfo info;
  if (described != nullptr) {
    info = described->shared_memory();
  } else {
    try {
      info = describe_(within).shared_memory();
    } catch (const CastError& e) {
      fallback("the server did not say where it is: " + e.message(), kRetry);
      return nullptr;
    }
  }
  if (info.socket().empty()) {
    fallback("the server offers none (shared_memory.enabled is false there)", kRetryElsewhere);
    return nullptr;
  }
  std::chrono::milliseconds handshake = kConnectWait;
  if (within) {
    // What the question left of the call's time.
    handshake = std::min(handshake, *within - std::chrono::duration_cast<std::chrono::milliseconds>(Clock::now() - started));
    if (handshake.count() <= 0) {
      fallback("no time was left for the handshake in the call that asked for it", kRetry);
      return nullptr;
    }
  }
  try {
    const std::string token = tokens_->token();
    auto session = connectShared(info, token, endpoint_, handshake);
    session->setToken(token);
    log_.debug("values of at least " + std::to_string(session->threshold()) +
               " bytes travel by shared memory with " + endpoint_);
    return session;
  } catch (const NoSession& e) {
    fallback(e.what(), e.elsewhere ? kRetryElsewhere : kRetry);
    return nullptr;
  }
}

void SharedLink::fallback(const std::string& why, std::chrono::seconds retry, bool forever) {
  bool tell = false;
  {
    std::lock_guard<std::mutex> lock(mu_);
    reason_ = why;
    forever_ = forever_ || forever;
    retryAt_ = Clock::now() + retry;
    tell = !told_;
    told_ = true;
  }
  if (tell) {
    log_.info("shared memory with the server at " + endpoint_ + " is not used (" + why +
              "): values travel as bytes");
  }
}

std::unique_ptr<ReadCall> SharedLink::read(Within within, bool currentToken) {
  std::shared_ptr<ClientSession> s = currentToken ? writerSession(within) : session(within);
  return s ? s->newCall() : nullptr;
}

void SharedLink::check() {
  std::shared_ptr<ClientSession> s;
  {
    std::lock_guard<std::mutex> lock(mu_);
    s = session_;
  }
  if (s) s->poll();
}

std::string SharedLink::reason() const {
  std::lock_guard<std::mutex> lock(mu_);
  return reason_;
}

std::shared_ptr<ClientSession> SharedLink::writerSession(Within within) {
  std::shared_ptr<ClientSession> s = session(within);
  if (s && s->token() != tokens_->token()) {
    renew(kRenewDrain);
    s = session(within);
  }
  return s;
}

std::shared_ptr<ClientSession> SharedLink::current() const {
  std::lock_guard<std::mutex> lock(mu_);
  return session_ && !session_->dead() ? session_ : nullptr;
}

void SharedLink::renew(std::chrono::milliseconds drain) {
  std::shared_ptr<ClientSession> s;
  {
    std::lock_guard<std::mutex> lock(mu_);
    s.swap(session_);
  }
  if (!s) return;
  s->writes().drain(drain);
  s->close();
}

void SharedLink::close() {
  std::shared_ptr<ClientSession> s;
  {
    std::lock_guard<std::mutex> lock(mu_);
    closed_ = true;
    s.swap(session_);
  }
  if (s) s->close();
}

// ------------------------------------------------------------------ writes

namespace {

// Stages `size` bytes, written by `fill`, in the session of `link` when the
// value is large enough and fits (recorded in `staged`); false: the bytes go
// in the request.
bool stage(SharedLink& link, std::size_t size, const std::function<void(std::uint8_t*)>& fill, Staging& staged,
           SharedLink::Within within) {
  std::shared_ptr<ClientSession> session = link.writerSession(within);
  if (!session || size < session->threshold()) return false;
  std::optional<Staged> region = session->stage(size, fill);
  if (!region) return false;
  staged.emplace_back(std::move(session), *region);
  return true;
}

// The same for a value given as its bytes.
bool stage(SharedLink& link, const std::string& data, Staging& staged, SharedLink::Within within) {
  return stage(
      link, data.size(), [&](std::uint8_t* out) { std::memcpy(out, data.data(), data.size()); }, staged, within);
}

// The value fields of an add or overwrite (of a request or a batch item).
template <class Item>
std::pair<google::protobuf::Any*, v1::StagedValue*> valueOf(Item* item) {
  if (item->has_add()) return {item->mutable_add()->mutable_value(), item->mutable_add()->mutable_staged_value()};
  return {item->mutable_overwrite()->mutable_value(), item->mutable_overwrite()->mutable_staged_value()};
}

// The request `build` makes for the value staged last: its bytes left out, the region named instead.
v1::WriteRequest stagedRequest(Staging& staged, const std::function<v1::WriteRequest(const std::string&)>& build) {
  static const std::string kNone;
  v1::WriteRequest request = build(kNone);
  staged.back().first->describe(staged.back().second, valueOf(&request).second);
  return request;
}

}  // namespace

v1::WriteRequest stagedWrite(SharedLink& link, const std::string& data, Staging& staged,
                             const std::function<v1::WriteRequest(const std::string& bytes)>& build,
                             SharedLink::Within within) {
  if (!stage(link, data, staged, within)) return build(data);
  return stagedRequest(staged, build);
}

v1::WriteRequest stagedMessage(SharedLink& link, const google::protobuf::Message& value, Staging& staged,
                               const std::function<v1::WriteRequest(const std::string& bytes)>& build,
                               SharedLink::Within within) {
  const std::size_t size = value.ByteSizeLong();  // caches the sizes SerializeWithCachedSizesToArray uses
  if (!stage(link, size, [&](std::uint8_t* out) { value.SerializeWithCachedSizesToArray(out); }, staged, within)) {
    return build(value.SerializeAsString());
  }
  return stagedRequest(staged, build);
}

std::unique_ptr<LoanState> placeLoan(SharedLink& link, std::string header, std::size_t size,
                                     SharedLink::Within within) {
  std::shared_ptr<ClientSession> session = link.writerSession(within);
  if (session && header.size() + size >= session->threshold()) {
    if (std::optional<Reserved> region = session->reserve(header.size() + size, header.size())) {
      return std::make_unique<LoanState>(header, size, session, std::move(*region));
    }
  }
  return privateLoan(std::move(header), size);
}

v1::WriteRequest loanedWrite(SharedLink& link, LoanState& loan, Staging& staged,
                             const std::function<v1::WriteRequest(const std::string& bytes)>& build,
                             SharedLink::Within within) {
  if (loan.shared()) {
    std::shared_ptr<ClientSession> writer = link.writerSession(within);
    if (writer) writer->poll();  // as a staged write does: a session the server ended is noticed first
    if (std::optional<Staged> region = loan.handOver(writer)) {
      staged.emplace_back(std::move(writer), *region);
      return stagedRequest(staged, build);
    }
  }
  return stagedWrite(link, loan.takeBytes(), staged, build, within);
}

v1::WriteRequest stagedBatch(SharedLink& link, const std::vector<BatchOp>& ops, Staging& staged,
                             SharedLink::Within within) {
  v1::WriteRequest request = batchRequest(ops);
  for (std::size_t i = 0; i < ops.size(); ++i) {
    if (ops[i].operation == Operation::Delete || !stage(link, ops[i].data, staged, within)) continue;
    auto [value, named] = valueOf(request.mutable_batch()->mutable_operations(static_cast<int>(i)));
    value->clear_value();
    staged.back().first->describe(staged.back().second, named);
  }
  return request;
}

void unstage(const Staging& staged, const CastError* error) {
  const bool known = error == nullptr || (error->code() != "UNAVAILABLE" && error->code() != "DEADLINE_EXCEEDED");
  for (const auto& [session, region] : staged) session->unstage(region, known);
}

}  // namespace cast::detail
