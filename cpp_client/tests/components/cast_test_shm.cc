// cast_test_shm: a writer or a reader of large values as a process of its
// own, the C++ peer of tests/interop/test_shared_memory_interop.py. The same
// arguments and lines as tests/reliability/components/shm_peer.py (Python)
// and cast.itest.ShmPeer (Java), so a test drives any of them:
//
//   cast_test_shm write N [change] [loan]
//                            adds "img" (or overwrites it if it exists) and
//                            overwrites it, N values of 1 MiB in all (value k
//                            is frame(k)), printing "WROTE k" after each and
//                            "DONE" at the end; stays until stdin closes.
//                            "change": once each write was acknowledged, it
//                            writes 0xFF over all of its staging area and
//                            prints "CHANGED k bytes" before "WROTE k".
//                            "loan": each value is made in a loan
//                            (Component::loan) and the loan written.
//   cast_test_shm read [hold|trywrite]
//                            watches "img" with its entry; prints "WATCHING"
//                            once the watch is confirmed, then per value
//                            "GOT revision k shared same sum": k which frame
//                            the view's field 1 is (-1: bytes that are no
//                            frame), shared 1 if it came by shared memory,
//                            same 1 if the decoded entry (entry<BytesValue>)
//                            has the view's bytes, sum a checksum of every
//                            byte read through the view; then "MISMATCH
//                            revision" if the view and the decoded entry
//                            differ. "hold" keeps a view
//                            of every value; "trywrite" tries, on the first
//                            value lent, to write the memory it is in, and
//                            prints "WRITE mprotect=R pwrite=R mmap=R child=R"
//                            (R: the errno name of the refusal, "allowed" if
//                            it was not refused; child: how a child process
//                            writing through the view ended). "FAILED reason"
//                            if the watch fails. Stays until stdin closes.
//   cast_test_shm get        reads "img" with getView and get<BytesValue>;
//                            prints "READ k shared same".
//   cast_test_shm deadline SA MS
//                            two connections of its own (cast::connect as
//                            $CAST_COMPONENT_ID-get and -add of
//                            $CAST_SUBARCHITECTURE, tokens minted from
//                            $CAST_SECRET, call timeout MS), with no
//                            shared-memory session with SA's server yet (the
//                            add connection wrote a small value of the type
//                            in its own SA: the type is registered); prints
//                            "READY", and at the line "go" a get and a 1 MiB
//                            add on SA at once, each "CALL get|add
//                            ErrorName|ok milliseconds", then "CALLED".
//
// With the launch contract (CAST_*) in its environment, as `cast run` starts
// a component.
#include <fcntl.h>
#include <google/protobuf/wrappers.pb.h>
#include <signal.h>
#include <sys/mman.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <functional>
#include <iostream>
#include <mutex>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "cast/cast.h"

namespace {

constexpr std::size_t kSize = 1 << 20;

std::mutex outMu;

void say(const std::string& line) {
  std::lock_guard<std::mutex> lock(outMu);
  std::cout << line << std::endl;
}

// The bytes of frame k: a pattern that differs in every byte position from
// frame to frame (shm_peer.py's frame()).
std::string frame(int k) {
  std::string unit(253, '\0');
  for (int i = 0; i < 253; ++i) unit[static_cast<std::size_t>(i)] = static_cast<char>((k * 7 + i) % 253);
  std::string out;
  out.reserve(kSize);
  for (std::size_t n = 0; n < kSize / 253; ++n) out += unit;
  return out;
}

// Which frame `data` is, or -1.
int which(std::string_view data) {
  for (int k = 0; k < 256; ++k) {
    const std::string f = frame(k);
    if (data.substr(0, 16) == std::string_view(f).substr(0, 16)) return data == f ? k : -1;
  }
  return -1;
}

// Every byte read: a checksum a compiler cannot leave out.
std::uint64_t checksum(cast::ByteSpan bytes) {
  std::uint64_t sum = 0;
  for (std::byte b : bytes) sum = sum * 31 + static_cast<std::uint8_t>(b);
  return sum;
}

std::string errnoName(int error) {
  switch (error) {
    case EPERM: return "EPERM";
    case EACCES: return "EACCES";
    case EINVAL: return "EINVAL";
    case EBADF: return "EBADF";
    case ENOENT: return "ENOENT";
    default: return "errno" + std::to_string(error);
  }
}

// The mapping (start-end, as /proc/self/maps writes it) that holds `address`.
std::string mappingOf(const void* address) {
  std::ifstream maps("/proc/self/maps");
  std::string line;
  const auto at = reinterpret_cast<std::uintptr_t>(address);
  while (std::getline(maps, line)) {
    const std::string range = line.substr(0, line.find(' '));
    const auto dash = range.find('-');
    const std::uintptr_t start = std::stoull(range.substr(0, dash), nullptr, 16);
    const std::uintptr_t end = std::stoull(range.substr(dash + 1), nullptr, 16);
    if (start <= at && at < end) return range;
  }
  return "";
}

// The /proc/self/map_files paths of this process's mappings of the server's
// `kind` memory files ("staging", "arena").
std::vector<std::string> memoryFiles(const std::string& kind) {
  std::ifstream maps("/proc/self/maps");
  std::vector<std::string> out;
  std::string line;
  while (std::getline(maps, line)) {
    if (line.find("memfd:cast-" + kind) != std::string::npos) {
      out.push_back("/proc/self/map_files/" + line.substr(0, line.find(' ')));
    }
  }
  return out;
}

// Writes 0xFF over every staging area this process has mapped, through the
// memory file (the same pages as the library's mapping); the bytes written.
std::size_t changeStaging() {
  std::size_t written = 0;
  for (const std::string& path : memoryFiles("staging")) {
    const int fd = ::open(path.c_str(), O_RDWR | O_CLOEXEC);
    if (fd < 0) continue;
    const off_t size = ::lseek(fd, 0, SEEK_END);
    const std::string ones(static_cast<std::size_t>(size > 0 ? size : 0), '\xff');
    if (::pwrite(fd, ones.data(), ones.size(), 0) == static_cast<ssize_t>(ones.size())) written += ones.size();
    ::close(fd);
  }
  return written;
}

// Tries every way to write the memory a lent value is in (write_test in
// the interop test): each must be refused.
std::string tryWrite(const cast::ValueView& view) {
  const cast::ByteSpan bytes = view.data();
  const long page = ::sysconf(_SC_PAGESIZE);
  auto* first = reinterpret_cast<void*>(reinterpret_cast<std::uintptr_t>(bytes.data()) & ~static_cast<std::uintptr_t>(page - 1));
  std::ostringstream out;
  out << "WRITE";
  // 1. Make the mapping writable.
  out << " mprotect=" << (::mprotect(first, static_cast<std::size_t>(page), PROT_READ | PROT_WRITE) == 0
                              ? "allowed"
                              : errnoName(errno));
  // 2. Open the memory file behind the mapping again, read-write, and write to it.
  const std::string range = mappingOf(bytes.data());
  const int fd = ::open(("/proc/self/map_files/" + range).c_str(), O_RDWR | O_CLOEXEC);
  if (fd < 0) {
    out << " pwrite=open:" << errnoName(errno) << " mmap=open:" << errnoName(errno);
  } else {
    const char x = 'x';
    out << " pwrite=" << (::pwrite(fd, &x, 1, 0) == 1 ? "allowed" : errnoName(errno));
    void* again = ::mmap(nullptr, static_cast<std::size_t>(page), PROT_READ | PROT_WRITE, MAP_SHARED, fd, 0);
    out << " mmap=" << (again != MAP_FAILED ? "allowed" : errnoName(errno));
    if (again != MAP_FAILED) ::munmap(again, static_cast<std::size_t>(page));
    ::close(fd);
  }
  // 3. Write through the view itself (in a child, which the kernel stops).
  std::cout.flush();
  const pid_t child = ::fork();
  if (child == 0) {
    *const_cast<volatile std::byte*>(bytes.data()) = std::byte{0x55};
    ::_exit(0);
  }
  int status = 0;
  ::waitpid(child, &status, 0);
  if (WIFSIGNALED(status)) {
    out << " child=" << (WTERMSIG(status) == SIGSEGV ? "SIGSEGV" : "signal" + std::to_string(WTERMSIG(status)));
  } else {
    out << " child=exit" << WEXITSTATUS(status) << (WEXITSTATUS(status) == 0 ? "(allowed)" : "");
  }
  return out.str();
}

class Peer : public cast::UnmanagedComponent {
 public:
  void watchFailed(const cast::CastError& error) override { say(std::string("FAILED ") + error.name() + ": " + error.message()); }
};

void waitForStdinEnd() {
  std::string line;
  while (std::getline(std::cin, line)) {
  }
}

int writeMode(Peer& peer, int n, bool change, bool loaned) {
  for (int k = 0; k < n; ++k) {
    google::protobuf::BytesValue value;
    const bool exists = k > 0 || peer.exists("img");
    if (loaned) {
      const std::string bytes = frame(k);
      cast::Loan loan = peer.loan(value, "value", bytes.size());
      std::memcpy(loan.buffer().data(), bytes.data(), bytes.size());
      exists ? peer.overwrite("img", std::move(loan)) : peer.add("img", std::move(loan));
    } else {
      value.set_value(frame(k));
      exists ? peer.overwrite("img", value) : peer.add("img", value);
    }
    if (change) say("CHANGED " + std::to_string(k) + " " + std::to_string(changeStaging()));
    say("WROTE " + std::to_string(k));
  }
  say("DONE");
  waitForStdinEnd();
  return 0;
}

int readMode(Peer& peer, const std::string& option) {
  std::mutex mu;
  std::vector<cast::ValueView> held;
  bool tried = false;
  peer.onChange(cast::addressFilter("img", {cast::Operation::Add, cast::Operation::Overwrite}).withEntry(),
                [&](const cast::WorkingMemoryChange& change) {
                  cast::ValueView view = change.view();
                  const cast::ByteSpan pixels = view.field(1);
                  const int k = which(pixels.chars());
                  const bool same = change.entry<google::protobuf::BytesValue>().value.value() == pixels.chars();
                  std::ostringstream line;
                  line << "GOT " << change.revision() << " " << k << " " << (view.shared() ? 1 : 0) << " "
                       << (same ? 1 : 0) << " " << checksum(view.data());
                  say(line.str());
                  if (!same) say("MISMATCH " + std::to_string(change.revision()));
                  std::lock_guard<std::mutex> lock(mu);
                  if (option == "trywrite" && view.shared() && !tried) {
                    tried = true;
                    say(tryWrite(view));
                    say("AFTER " + std::to_string(which(view.field(1).chars())));
                  }
                  if (option == "hold") held.push_back(std::move(view));
                });
  say("WATCHING");
  waitForStdinEnd();
  return 0;
}

int getMode(Peer& peer) {
  {
    const cast::ValueView view = peer.getView("img");
    const int k = which(view.field(1).chars());
    const bool same = peer.get<google::protobuf::BytesValue>("img").value() == view.field(1).chars();
    say("READ " + std::to_string(k) + " " + (view.shared() ? "1" : "0") + " " + (same ? "1" : "0"));
  }  // the view gives the value back here
  waitForStdinEnd();
  return 0;
}

std::string env(const char* name) {
  const char* value = std::getenv(name);
  return value != nullptr ? value : "";
}

// Two fresh connections, then a get and a 1 MiB add at once at "go": how
// each ended, and when.
int deadlineMode(const std::string& sa, int timeoutMs) {
  auto open = [&](const std::string& name) {
    cast::ConnectOptions options;
    options.componentId = env("CAST_COMPONENT_ID") + "-" + name;
    options.subarchitecture = env("CAST_SUBARCHITECTURE");
    options.callTimeout = std::chrono::milliseconds(timeoutMs);
    return cast::connect(options);
  };
  std::unique_ptr<cast::Connection> getter = open("get");
  std::unique_ptr<cast::Connection> adder = open("add");
  // The value's type is registered with every server by the first write of
  // it: done now, in the own SA, so that the add below meets the stopped
  // server first when it opens the session.
  google::protobuf::BytesValue warm;
  warm.set_value("warm");
  adder->add(env("CAST_COMPONENT_ID") + "-warm", warm);
  say("READY");
  std::string line;
  while (std::getline(std::cin, line) && line != "go") {
  }
  auto timed = [](const std::string& name, const std::function<void()>& call) {
    const auto started = std::chrono::steady_clock::now();
    std::string outcome = "ok";
    try {
      call();
    } catch (const cast::CastError& e) {
      outcome = e.name();
    }
    const auto ms = std::chrono::duration_cast<std::chrono::milliseconds>(std::chrono::steady_clock::now() - started);
    say("CALL " + name + " " + outcome + " " + std::to_string(ms.count()));
  };
  std::thread get([&] { timed("get", [&] { getter->get<google::protobuf::BytesValue>("deadline", sa); }); });
  std::thread add([&] {
    google::protobuf::BytesValue value;
    value.set_value(frame(0));
    timed("add", [&] { adder->add("deadline", value, sa); });
  });
  get.join();
  add.join();
  say("CALLED");
  waitForStdinEnd();
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  if (argc < 2) {
    std::cerr << "usage: cast_test_shm write N [change] [loan] | read [hold|trywrite] | get | deadline SA MS\n";
    return 2;
  }
  const std::string mode = argv[1];
  try {
    if (mode == "deadline" && argc > 3) return deadlineMode(argv[2], std::stoi(argv[3]));
    Peer peer;
    peer.bind(cast::LaunchContract::fromEnv().connect());
    int code = 2;
    if (mode == "write" && argc > 2) {
      const std::vector<std::string> options(argv + 3, argv + argc);
      const auto has = [&](const char* option) { return std::find(options.begin(), options.end(), option) != options.end(); };
      code = writeMode(peer, std::stoi(argv[2]), has("change"), has("loan"));
    }
    if (mode == "read") code = readMode(peer, argc > 2 ? argv[2] : "");
    if (mode == "get") code = getMode(peer);
    peer.close();
    return code;
  } catch (const cast::CastError& e) {
    std::cerr << "cast_test_shm: " << e.name() << ": " << e.message() << std::endl;
    return 1;
  }
}
