// The frames of a shared-memory session (shm_wire.h).
#include "shm_wire.h"

#include <sys/socket.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <system_error>

namespace cast::detail::shm {

namespace {

// Little-endian fields, whatever the machine's order.
void putU16(std::string& out, std::uint16_t v) {
  for (int i = 0; i < 2; ++i) out.push_back(static_cast<char>((v >> (8 * i)) & 0xff));
}
void putU32(std::string& out, std::uint32_t v) {
  for (int i = 0; i < 4; ++i) out.push_back(static_cast<char>((v >> (8 * i)) & 0xff));
}
void putU64(std::string& out, std::uint64_t v) {
  for (int i = 0; i < 8; ++i) out.push_back(static_cast<char>((v >> (8 * i)) & 0xff));
}
std::uint64_t getLe(const std::string& s, std::size_t at, int bytes) {
  std::uint64_t v = 0;
  for (int i = bytes - 1; i >= 0; --i) v = (v << 8) | static_cast<unsigned char>(s[at + static_cast<std::size_t>(i)]);
  return v;
}

std::string frame(std::uint8_t kind, const std::string& body) {
  std::string out;
  out.reserve(5 + body.size());
  putU32(out, static_cast<std::uint32_t>(body.size() + 1));
  out.push_back(static_cast<char>(kind));
  out += body;
  return out;
}

bool carriesFd(std::uint8_t kind) { return kind == kWelcome || kind == kSegment; }

// Descriptors a control buffer of recvmsg takes: 16 (docs/client-protocol.md).
constexpr std::size_t kFdsPerRead = 16;

}  // namespace

std::string hello(const std::string& token) {
  std::string body;
  putU16(body, kVersion);
  body += token;
  return frame(kHello, body);
}

std::string release(const std::vector<std::uint64_t>& valueIds) {
  std::string body;
  body.reserve(8 * valueIds.size());
  for (std::uint64_t id : valueIds) putU64(body, id);
  return frame(kRelease, body);
}

std::string received(std::uint64_t call, std::uint64_t count, bool ended) {
  std::string body;
  putU64(body, call);
  putU64(body, count);
  body.push_back(ended ? 1 : 0);
  return frame(kReceived, body);
}

std::string writes(const std::string& requests) { return frame(kWrites, requests); }

Welcome parseWelcome(const std::string& body) {
  if (body.size() != 2 + 16 + 16 + 3 * 8) throw ProtocolError("WELCOME has the wrong size");
  Welcome w;
  w.version = static_cast<std::uint16_t>(getLe(body, 0, 2));
  w.session = body.substr(2, 16);
  w.serverId = body.substr(18, 16);
  w.threshold = getLe(body, 34, 8);
  w.window = getLe(body, 42, 8);
  w.staging = getLe(body, 50, 8);
  return w;
}

std::pair<std::uint32_t, std::uint64_t> parseSegment(const std::string& body) {
  if (body.size() != 12) throw ProtocolError("SEGMENT has the wrong size");
  return {static_cast<std::uint32_t>(getLe(body, 0, 4)), getLe(body, 4, 8)};
}

std::uint32_t parseRetire(const std::string& body) {
  if (body.size() != 4) throw ProtocolError("RETIRE has the wrong size");
  return static_cast<std::uint32_t>(getLe(body, 0, 4));
}

std::uint64_t parseEventsCall(const std::string& body) {
  if (body.size() < 8) throw ProtocolError("EVENTS is shorter than its call number");
  return getLe(body, 0, 8);
}

std::size_t maxFrame(std::uint8_t kind) {
  return kind == kWrites || kind == kReplies || kind == kEvents ? kMaxWritesFrame : kMaxFrame;
}

std::string hex(const std::string& bytes) {
  static const char digits[] = "0123456789abcdef";
  std::string out;
  out.reserve(2 * bytes.size());
  for (unsigned char c : bytes) {
    out.push_back(digits[c >> 4]);
    out.push_back(digits[c & 15]);
  }
  return out;
}

FrameReader::~FrameReader() { closeStray(); }

std::vector<Frame> FrameReader::feed(const char* data, std::size_t size, std::vector<int> fds) {
  buf_.append(data, size);
  fds_.insert(fds_.end(), fds.begin(), fds.end());
  std::vector<Frame> out;
  std::size_t at = 0;
  while (buf_.size() - at >= 4) {
    const std::uint64_t length = getLe(buf_, at, 4);
    if (length < 1 || length > kMaxWritesFrame) {
      throw ProtocolError("frame of " + std::to_string(length) + " bytes (1 to " + std::to_string(kMaxWritesFrame) +
                          " allowed)");
    }
    if (buf_.size() - at < 5) break;  // the kind decides the bound
    const auto kind = static_cast<std::uint8_t>(buf_[at + 4]);
    const std::size_t limit = maxFrame(kind);
    if (length > limit) {
      throw ProtocolError("frame of kind " + std::to_string(kind) + " has " + std::to_string(length) +
                          " bytes (1 to " + std::to_string(limit) + " allowed)");
    }
    if (buf_.size() - at - 4 < length) break;
    Frame f;
    f.kind = static_cast<std::uint8_t>(buf_[at + 4]);
    f.body = buf_.substr(at + 5, length - 1);
    at += 4 + length;
    if (carriesFd(f.kind)) {
      if (fds_.empty()) {
        for (auto& done : out) {
          if (done.fd >= 0) ::close(done.fd);
        }
        throw ProtocolError("frame of kind " + std::to_string(f.kind) + " came without its memory file");
      }
      f.fd = fds_.front();
      fds_.pop_front();
    }
    out.push_back(std::move(f));
  }
  buf_.erase(0, at);
  return out;
}

void FrameReader::closeStray() {
  for (int fd : fds_) ::close(fd);
  fds_.clear();
}

Inbox::Inbox(std::size_t capacity) : buf_(new char[capacity]), capacity_(capacity) {}

std::optional<std::vector<int>> Inbox::receive(int fd) {
  size_ = 0;
  alignas(cmsghdr) char control[CMSG_SPACE(kFdsPerRead * sizeof(int))];
  iovec iov{buf_.get(), capacity_};
  msghdr msg{};
  msg.msg_iov = &iov;
  msg.msg_iovlen = 1;
  msg.msg_control = control;
  msg.msg_controllen = sizeof control;
  ssize_t n;
  do {
    n = ::recvmsg(fd, &msg, MSG_CMSG_CLOEXEC);
  } while (n < 0 && errno == EINTR);
  if (n < 0) {
    if (errno == EAGAIN || errno == EWOULDBLOCK) return std::nullopt;
    throw std::system_error(errno, std::generic_category(), "recvmsg");
  }
  size_ = static_cast<std::size_t>(n);
  std::vector<int> fds;
  for (cmsghdr* c = CMSG_FIRSTHDR(&msg); c != nullptr; c = CMSG_NXTHDR(&msg, c)) {
    if (c->cmsg_level != SOL_SOCKET || c->cmsg_type != SCM_RIGHTS) continue;
    const std::size_t count = (c->cmsg_len - CMSG_LEN(0)) / sizeof(int);
    for (std::size_t i = 0; i < count; ++i) {
      int received;
      std::memcpy(&received, CMSG_DATA(c) + i * sizeof(int), sizeof(int));
      fds.push_back(received);
    }
  }
  if (msg.msg_flags & MSG_CTRUNC) {
    for (int d : fds) ::close(d);
    throw ProtocolError("more memory files arrived than one read takes");
  }
  return fds;
}

}  // namespace cast::detail::shm
