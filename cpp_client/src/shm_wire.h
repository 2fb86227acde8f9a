// The frames of a shared-memory session on a server's Unix socket
// (docs/client-protocol.md, "Large values by shared memory", "Frames").
// Mirrors python/cast/wire/shared_memory.py; no gRPC, no protobuf.
//
// Every frame is a little-endian u32 length (of what follows, 1 to 65,536),
// a u8 kind and its fields. A frame that carries a memory file arrives with
// the descriptor as SCM_RIGHTS, no later than its first byte: a reader keeps
// the descriptors it received in order and gives the next one to each frame
// of a kind that carries one.
#pragma once

#include <cstddef>
#include <cstdint>
#include <deque>
#include <memory>
#include <optional>
#include <stdexcept>
#include <string>
#include <vector>

namespace cast::detail::shm {

// The protocol's version, sent in HELLO and WELCOME.
inline constexpr std::uint16_t kVersion = 1;

// Frame kinds. Client -> server:
inline constexpr std::uint8_t kHello = 1;     // u16 version, then the token (UTF-8) to the end
inline constexpr std::uint8_t kRelease = 2;   // n x u64 value ids given back
inline constexpr std::uint8_t kReceived = 3;  // u64 call, u64 count, u8 ended
inline constexpr std::uint8_t kWrites = 4;    // a serialized cast.v1.WriteRequests
// Server -> client:
inline constexpr std::uint8_t kWelcome = 10;  // u16 version, 16 B session, 16 B server id, u64 x 3; 1 fd
inline constexpr std::uint8_t kRefused = 11;  // the reason (UTF-8) to the end
inline constexpr std::uint8_t kSegment = 12;  // u32 segment, u64 size; 1 fd
inline constexpr std::uint8_t kRetire = 13;   // u32 segment
inline constexpr std::uint8_t kReplies = 14;  // a serialized cast.v1.WriteReplies
inline constexpr std::uint8_t kEvents = 15;   // u64 call, then a serialized cast.v1.WatchResponse

// The largest frame either side sends or accepts (a RELEASE of 8,000 ids
// fits), but WRITES, REPLIES and EVENTS.
inline constexpr std::size_t kMaxFrame = 1 << 16;
// The largest WRITES, REPLIES or EVENTS frame: a gRPC message's limit, so
// that any request the Write stream takes, and any batch a Watch call would
// carry, fits one.
inline constexpr std::size_t kMaxWritesFrame = std::size_t{64} << 20;
// The most value ids one RELEASE frame carries.
inline constexpr std::size_t kMaxReleaseIds = 8000;

// A frame that breaks the protocol: the session ends.
class ProtocolError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

// One decoded frame: its kind, its fields (after the kind byte), and the
// memory file it carries (-1: none). The receiver owns the descriptor.
struct Frame {
  std::uint8_t kind = 0;
  std::string body;
  int fd = -1;
};

// What WELCOME says.
struct Welcome {
  std::uint16_t version = 0;
  std::string session;   // 16 bytes
  std::string serverId;  // 16 bytes
  std::uint64_t threshold = 0;
  std::uint64_t window = 0;
  std::uint64_t staging = 0;
};

// Frames to send.
std::string hello(const std::string& token);
std::string release(const std::vector<std::uint64_t>& valueIds);
std::string received(std::uint64_t call, std::uint64_t count, bool ended);
// WRITES: a serialized WriteRequests (socket_writes.h).
std::string writes(const std::string& requests);

// Fields of received frames; ProtocolError when the size is wrong.
Welcome parseWelcome(const std::string& body);
// (segment id, size) of a SEGMENT.
std::pair<std::uint32_t, std::uint64_t> parseSegment(const std::string& body);
std::uint32_t parseRetire(const std::string& body);
// The call number of an EVENTS frame; its batch (a serialized WatchResponse)
// is the body after those 8 bytes.
std::uint64_t parseEventsCall(const std::string& body);
// The largest frame of `kind` a receiver accepts.
std::size_t maxFrame(std::uint8_t kind);

// 32 lowercase hex digits of 16 bytes (how WELCOME's ids are compared and named).
std::string hex(const std::string& bytes);

// Bytes and descriptors in (from recvmsg), whole frames out, each with the
// descriptor it carries. Not thread-safe.
class FrameReader {
 public:
  FrameReader() = default;
  ~FrameReader();
  FrameReader(const FrameReader&) = delete;
  FrameReader& operator=(const FrameReader&) = delete;

  // Adds what one read gave (it takes the descriptors); the frames now
  // complete. ProtocolError for a length out of range or a frame of a kind
  // that carries a descriptor without one.
  std::vector<Frame> feed(const char* data, std::size_t size, std::vector<int> fds);
  // Closes the descriptors no frame claimed.
  void closeStray();

 private:
  std::string buf_;
  std::deque<int> fds_;
};

// A buffer one socket's reads go into, kept from read to read (one reader
// at a time): a read neither allocates nor clears memory. Mirrors the Python
// client's wire.shared_memory.Inbox.
class Inbox {
 public:
  explicit Inbox(std::size_t capacity = kMaxFrame);

  // One recvmsg on `fd` (non-blocking or not): the bytes read (data(),
  // size(); none: the peer closed), valid until the next read, and the
  // descriptors that came with them. nullopt when nothing is there yet
  // (EAGAIN); ProtocolError when more descriptors came than the control
  // buffer takes (they are closed); std::system_error for a failed read.
  std::optional<std::vector<int>> receive(int fd);

  const char* data() const { return buf_.get(); }
  // What the last read gave.
  std::size_t size() const { return size_; }
  // Whether the last read filled the buffer; if not, the socket held no more
  // when it was read (or what follows came with descriptors: a read stops
  // after those), so a reader may wait for it to be readable again rather
  // than read once more to learn it is empty.
  bool full() const { return size_ == capacity_; }

 private:
  std::unique_ptr<char[]> buf_;
  std::size_t capacity_;
  std::size_t size_ = 0;
};

}  // namespace cast::detail::shm
