// One session with a server's shared memory, after its WELCOME
// (docs/client-protocol.md, "Large values by shared memory"). Private to the
// gRPC transport. Mirrors the Python client's client/shm_session.py.
//
// A ClientSession
// - stages a large value: copies it into a free region of the staging area
//   (a memory file the server made for the session, mapped read-write here)
//   and names it in the write (StagedValue); the region is reused once the
//   write's reply came, never while its outcome is unknown;
// - claims a value the server lent (SharedValue in an entry): the bytes in a
//   segment mapped once, read-only, when its SEGMENT frame came, held by a
//   Lease that gives the value back (RELEASE) when the last holder of it (an
//   entry, a change, a ValueView) is gone;
// - counts the references each read call received and says so when the call
//   ends (RECEIVED), so that the server takes back what never arrived.
//
// - carries the component's writes once it has a session (socket_writes.h),
//   and its gets when the server answers them there (reads());
// - hands the EVENTS frames of a Watch call that asked for them to that call's
//   receiver (docs/client-protocol.md, "A watch's events on the session's
//   socket").
//
// A Watch call taking its events here hands the session to the component's
// dispatcher thread, which waits on the socket while it has nothing to run
// and handles what comes itself, so that an event's callback runs on the
// thread the kernel woke for its frame (dispatcher.h). No thread of its own
// until the first pipelined write on its socket (or a Watch call with no
// dispatcher to read it): from then on its reader thread waits on the socket
// too and handles what comes, on that thread (a watch's events go from it
// straight to the component's queue). Until then what the server sends
// (SEGMENT, RETIRE, REFUSED, the end) is read whenever the session is used;
// any thread that uses it may read it. How a session is opened, and when
// there is none: shm.h.
#pragma once

#include <atomic>
#include <chrono>
#include <cstddef>
#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <string_view>
#include <thread>
#include <utility>
#include <vector>

#include "cast/types.h"
#include "cast/v1/entry.pb.h"
#include "cast/v1/working_memory.pb.h"
#include "event_source.h"
#include "shm_wire.h"
#include "socket_writes.h"

namespace cast::detail {

// The call metadata that names a read's session and call: "<session hex>/<call>".
inline constexpr char kSharedMemoryMetadata[] = "cast-shared-memory";
// The metadata with which a Watch call naming a session asks for its event
// batches as EVENTS frames on that session's socket.
inline constexpr char kWatchEventsMetadata[] = "cast-watch-events";
inline constexpr char kWatchEventsOnSocket[] = "socket";

// What takes the EVENTS frames of one Watch call.
struct EventsReceiver {
  // A frame's batch (a serialized WatchResponse), on the thread that read it,
  // in the order the frames came; never two at once.
  std::function<void(const char* data, std::size_t size)> batch;
  // The session ended (why): no more frames come.
  std::function<void(const std::string& why)> ended;
  // Waits up to the time given for room in the queue the batches go to; true
  // when there is. The reader thread reads the socket only while there is
  // room (or a write waits for its reply): what the server sends meanwhile
  // waits in the socket, then on the server.
  std::function<bool(std::chrono::milliseconds)> room;
  // Hands the session to the dispatcher thread that reads it from then on
  // (the component's); unset: the session's reader thread reads it.
  AttachSource attach;
};

// A region of mapped memory, unmapped when the last holder lets it go (a
// segment stays mapped while values lent in it are held, after RETIRE or the
// session's end too).
class Mapping {
 public:
  Mapping(void* address, std::size_t size) : address_(address), size_(size) {}
  ~Mapping();
  Mapping(const Mapping&) = delete;
  Mapping& operator=(const Mapping&) = delete;
  char* data() const { return static_cast<char*>(address_); }
  std::size_t size() const { return size_; }

 private:
  void* address_;
  std::size_t size_;
};

// First-fit allocation of whole-page extents in [0, size); not thread-safe.
// Few values are staged at once, so the linear scan costs nothing next to
// copying one.
class Extents {
 public:
  explicit Extents(std::size_t size);
  // The offset of a free extent of `size` bytes, or nullopt when none is left.
  std::optional<std::size_t> take(std::size_t size);
  // Frees an extent take() gave, merging it with its neighbours.
  void give(std::size_t offset, std::size_t size);
  std::size_t size() const { return size_; }
  std::size_t used() const { return used_; }

 private:
  std::size_t size_;
  std::size_t used_ = 0;
  std::map<std::size_t, std::size_t> free_;  // offset -> bytes
};

// `size` rounded up to whole 4 KiB pages (at least one).
std::size_t roundUpToPages(std::size_t size);

// A value staged for one write, until the write's reply came.
struct Staged {
  std::size_t offset = 0;
  std::size_t size = 0;   // the value's bytes
  std::size_t taken = 0;  // whole pages, from the region's start (offset - pad)
  // Bytes of the region before the value: a loan's, so that the loaned
  // field's bytes start on a 64-byte line (ClientSession::reserve); 0 else.
  std::size_t pad = 0;
};

// Where a loan's payload starts within the staging area: on a multiple of
// this (a cache line, as the server's arena places a value's largest bytes
// field), so that an array the writer makes over it is aligned.
inline constexpr std::size_t kLoanAlignment = 64;

// A region of the staging area reserved for a loan (ClientSession::reserve),
// and the staging area's mapping, which the loan keeps mapped.
struct Reserved {
  Staged staged;
  std::shared_ptr<Mapping> staging;
};

class ClientSession;

// One read call (a Get, a GetByType, a Watch stream): its metadata, and how
// many references it received. Used by one thread at a time.
class ReadCall {
 public:
  ReadCall(std::shared_ptr<ClientSession> session, std::uint64_t number);
  // Says the call ended (as end(false)) if end() was not called.
  ~ReadCall();
  ReadCall(const ReadCall&) = delete;
  ReadCall& operator=(const ReadCall&) = delete;

  // The metadata value that names it (under kSharedMemoryMetadata).
  const std::string& metadata() const { return metadata_; }
  std::uint64_t number() const { return number_; }
  const std::shared_ptr<ClientSession>& session() const { return session_; }
  // The bytes of a value lent on this call, held until the result is let go;
  // UnavailableError when they cannot be read (read again).
  std::shared_ptr<const LentBytes> claim(const v1::SharedValue& ref);
  // The call is over: the server takes back what it sent and this call never
  // received. `answered`: the whole answer was read, so nothing sent failed
  // to arrive; with no reference in it there is nothing to say.
  void end(bool answered);

 private:
  std::shared_ptr<ClientSession> session_;
  std::uint64_t number_;
  std::string metadata_;
  std::uint64_t count_ = 0;
  bool ended_ = false;
};

class ClientSession : public EventSource, public std::enable_shared_from_this<ClientSession> {
 public:
  // Takes `socket` (connected, its WELCOME read) and maps the staging area
  // `stagingFd` (closed here); std::system_error when it cannot be mapped.
  ClientSession(int socket, const shm::Welcome& welcome, int stagingFd, std::string endpoint);
  ~ClientSession();
  ClientSession(const ClientSession&) = delete;
  ClientSession& operator=(const ClientSession&) = delete;

  const std::string& id() const { return id_; }           // 16 bytes
  const std::string& serverId() const { return serverId_; }  // 32 hex digits
  std::uint64_t threshold() const { return threshold_; }
  std::uint64_t window() const { return window_; }
  std::size_t stagingBytes() const { return stagingSize_; }
  // The token its HELLO carried: the identity of the writes on its socket.
  const std::string& token() const { return token_; }
  void setToken(std::string token) { token_ = std::move(token); }
  // Whether the server answers gets in WRITES frames (SharedMemoryInfo.reads):
  // only then does a get go on this socket; a server of an earlier release
  // would refuse it as an empty request, so the get is a unary call.
  bool reads() const { return reads_.load(std::memory_order_relaxed); }
  void setReads(bool reads) { reads_.store(reads, std::memory_order_relaxed); }

  // ------------------------------------------------------------- writes
  // `data` copied into a free region of the staging area; nullopt when there
  // is no room or the session ended (send the bytes).
  std::optional<Staged> stage(std::string_view data);
  // The same for a value of `size` bytes that `fill` writes at the address it
  // is given (a message serialised straight into the staging area).
  std::optional<Staged> stage(std::size_t size, const std::function<void(std::uint8_t*)>& fill);
  // A region for a loan (cast/loan.h): room for a value of `size` bytes
  // whose byte `payload` (the loaned field's first) falls on a multiple of
  // kLoanAlignment within the staging area (Staged::pad before the value),
  // written by the loan's owner, not here; with the mapping, which keeps the
  // region's memory mapped while the loan lives, whatever ends the session
  // meanwhile. Given back by unstage(). nullopt when there is no room or the
  // session ended (the loan is private memory).
  std::optional<Reserved> reserve(std::size_t size, std::size_t payload);
  // What a write request says of a staged value.
  void describe(const Staged& staged, v1::StagedValue* out) const;
  // The write's reply came (`known`): its region is free again. Otherwise
  // (its stream broke, its deadline passed) it may still be applied later,
  // and the server would copy whatever the region then holds: it stays taken
  // until the session ends.
  void unstage(const Staged& staged, bool known);
  // Staged bytes of writes whose outcome is unknown (kept out of use).
  std::size_t quarantined() const;
  // Bytes of the staging area taken now (staged values, loans, and what is
  // quarantined), for tests and diagnostics; 0 once the session ended.
  std::size_t stagingUsed() const;
  // The staging area's mapping (nullptr once the session ended), for tests
  // and diagnostics: what the server reads a staged value from.
  std::shared_ptr<const Mapping> stagingArea() const;

  // The Write-stream requests sent on this session's socket (socket_writes.h).
  SessionWrites& writes() { return *writes_; }

  // -------------------------------------------------------------- reads
  // A read call on this session (its metadata names it).
  std::unique_ptr<ReadCall> newCall();
  // The bytes of a lent value and its lease; UnavailableError if its segment
  // never came, or the reference does not fit in it.
  std::shared_ptr<const LentBytes> claim(const v1::SharedValue& ref);
  // A lease is gone: RELEASE it. Never waits for another sender (leases go
  // on any thread): what it cannot send now, the sender in the way sends.
  void giveBack(std::uint64_t valueId);

  // ------------------------------------------------------------- events
  // The EVENTS frames of call `call` go to `receiver` from now on, read by
  // the dispatcher thread the receiver attaches the session to, or else by
  // the reader thread (started now if it is not running).
  void receiveEvents(std::uint64_t call, EventsReceiver receiver);
  // No more frames of `call` go to its receiver: returns once none is being
  // handed to it, and its `ended` is not called after.
  void stopEvents(std::uint64_t call);
  // EVENTS frames handed to a receiver in this process, for tests and
  // diagnostics (every session's).
  static std::uint64_t eventFramesHandled();
  // Reader threads started in this process (every session's), for tests and
  // diagnostics.
  static std::uint64_t readersStarted();
  // Reads of this session's socket so far (empty ones included), for tests
  // and diagnostics.
  std::uint64_t socketReads() const { return socketReads_.load(std::memory_order_relaxed); }

  // ------------------------------------------------------------- frames
  // Starts the thread that waits on the socket and handles what comes (the
  // writes' replies, a watch's events), unless it runs; it ends with the
  // session.
  void startReader();
  // Sends a frame (after the RELEASEs waiting); nothing once the session ended.
  void send(const std::string& frame);
  // Reads what the server sent (SEGMENT, RETIRE, REFUSED, the end); waits up
  // to `wait` for something when it is not zero. False, reading nothing,
  // when another thread reads the socket (it handles what comes).
  bool poll(std::chrono::milliseconds wait = std::chrono::milliseconds(0));
  // EventSource: the socket, -1 once the session ended; pump() is poll()
  // without a wait.
  int sourceFd() const override;
  bool pump() override;
  // Reads and handles what comes until `done()` or `wait` passed, on this
  // thread; false at once when another thread reads (it handles what comes).
  // A thread waiting for a write's reply reads it itself this way, rather
  // than be woken by the reader thread that read it.
  bool readUntil(const std::function<bool()>& done, std::chrono::milliseconds wait);
  // Whether a thread reads the socket now (it says so when it stops:
  // SessionWrites::readerLeft).
  bool reading() const { return reading_.load(); }
  // Whether the session ended, and why ("" while it lives).
  bool dead() const { return dead_.load(); }
  std::string why() const;
  // Segments mapped now (each once, however many values of it are held).
  std::size_t segments() const;
  // Ends the session (what it holds lent the server takes back).
  void close();
  // Ends it for `why` (a write got no reply in time), said at DEBUG.
  void abandon(const std::string& why);

 private:
  void handle(shm::Frame& frame);
  void events(const std::string& body);
  void end(const std::string& why);
  // One turn of the reader thread: the writes' deadlines, then what came.
  void readOnce();
  // Reads and handles every frame the socket holds now (readMu_ held).
  void readAvailable();
  // readMu_ is let go: say so to the writes waiting for a reader.
  void readerLeft();
  static void readLoop(const std::weak_ptr<ClientSession>& weak);
  void flushLocked();                          // sendMu_ held
  bool writeLocked(const std::string& frame);  // sendMu_ held
  void sendQueued();

  const std::string endpoint_;
  const int socket_;
  std::string id_;
  std::string idHex_;
  std::string serverId_;
  std::uint64_t threshold_ = 0;
  std::uint64_t window_ = 0;
  std::size_t stagingSize_ = 0;
  std::string token_;

  // The thread holding sendMu_ never lets a Lease go (it only writes to the
  // socket), so giveBack's try_lock never meets its own thread's lock.
  std::mutex sendMu_;
  std::mutex unsentMu_;  // guards unsent_
  std::vector<std::uint64_t> unsent_;  // value ids given back, not yet sent

  std::timed_mutex readMu_;  // one reader of the socket at a time; guards reader_ and inbox_
  std::atomic<std::thread::id> polling_{};  // the thread holding readMu_ to read (a claim there must not read again)
  shm::FrameReader reader_;

  // A batch is handed to its receiver under eventsMu_, its end under endMu_
  // (told from wherever the session ends, which may hold sendMu_).
  std::mutex eventsMu_;
  std::map<std::uint64_t, EventsReceiver> receivers_;
  std::mutex endMu_;
  std::map<std::uint64_t, std::function<void(const std::string&)>> enders_;

  std::mutex threadMu_;  // guards thread_ and stopped_
  std::thread thread_;   // the reader thread, once started
  bool stopped_ = false;
  shm::Inbox inbox_;  // what one read gave (kept: a read neither allocates nor clears memory)
  std::atomic<std::uint64_t> socketReads_{0};  // socketReads()

  mutable std::mutex stateMu_;  // guards what follows
  std::shared_ptr<Mapping> staging_;  // null once the session ended (loans and copies under way keep it mapped)
  Extents regions_;
  std::size_t quarantined_ = 0;
  std::map<std::uint32_t, std::shared_ptr<const Mapping>> segments_;
  std::uint64_t calls_ = 0;
  std::string why_;
  std::atomic<bool> dead_{false};
  std::atomic<bool> reading_{false};  // readMu_ is held to read (poll, readUntil)
  std::atomic<bool> reads_{false};    // reads()
  std::unique_ptr<SessionWrites> writes_;  // made with the session, gone before its socket is closed
};

}  // namespace cast::detail
