// cast_bench: the C++ client's side of benchmark M7 (bench/other_clients.py),
// measured like the Python client in bench/cast_cases.py (m1_sequential,
// m3_latency). Not a component of the library's API: a program that reads the
// launch contract (CAST_ENDPOINT, CAST_COMPONENT_ID, CAST_SUBARCHITECTURE,
// CAST_TOKEN), binds one component and runs one mode:
//
//   cast_bench add N            200 warm-up adds, then N sequential adds of a
//                               100-byte google.protobuf.BytesValue; prints
//                               {"calls": N, "seconds": S, "per_s": R}
//   cast_bench blocks WARM      WARM warm-up adds, then prints "ready" and reads
//                               stdin: for each line "B W", W untimed adds, then
//                               B sequential adds and one line with the seconds
//                               they took; ends at EOF
//                               (bench/other_clients.py interleaves these blocks
//                               with the other languages')
//   cast_bench watch N          onChange(addressFilter("lat")) in its SA; prints
//                               "ready" once the watch is confirmed, then after N
//                               events {"REVISION": NS, ...}, NS the
//                               steady_clock (CLOCK_MONOTONIC) time in the callback
//   cast_bench write N GAP_MS [WARM [TURN SIDES]]
//                               adds "lat", WARM overwrites back to back (not
//                               measured), then N-1 overwrites spaced by GAP_MS,
//                               stamping CLOCK_MONOTONIC just before each one;
//                               prints {"REVISION": NS, ...} (the measured ones).
//                               With TURN (1..SIDES) every overwrite is in its
//                               turn: the seconds whose number modulo SIDES is
//                               TURN - 1, from 70 ms into each (bench/turns.py;
//                               M7 measures the three languages' latencies so)
//
// Image-sized entries (M8, bench/images.py):
//
//   cast_bench image-write SIZE N GAP_US [WARM WARM_SIZE [COLD [BURST PAUSE_US [TURN]]]]
//                               adds "img" (a BytesValue of SIZE bytes), then
//                               COLD overwrites (default 0) paced as the N below
//                               (the readers' first seconds), WARM (default 0) of
//                               WARM_SIZE bytes back to back, in bursts of BURST
//                               (default: all of them), a pause of PAUSE_US
//                               between bursts, and one of 0.3 s (a warm-up on
//                               the watchers' real path), then N
//                               overwrites, the i-th started at start + i * GAP_US
//                               (0: back to back), each made (its bytes written
//                               in place, into a loan of the value's bytes: on
//                               the server's host the staging area the server
//                               copies it from, so the write copies nothing) and
//                               then stamped on CLOCK_MONOTONIC just before it
//                               (the warm-up's and the first seconds' overwrites
//                               the same way); deletes "img" (the watchers' end
//                               mark) and prints {"REVISION": NS, ...} (every
//                               overwrite, in that order: the reader of the stamps
//                               tells the three parts apart by revision). The
//                               values alternate: bytes of 1, of 2 (as
//                               bench/image_writer.py's, so that
//                               bench/shared_memory.py checks the watchers' sums).
//                               With TURN 1 (the even seconds) or 2 (the odd
//                               ones) it prints "warm" after the warm-up, reads
//                               one line of stdin, and writes the N only in its
//                               turn: from 70 ms into each of its seconds of
//                               CLOCK_MONOTONIC, the pace starting again there
//                               (bench/turns.py, which measures M8's judged
//                               phase and Zenoh's at once)
//   cast_bench image-watch DELIVERY
//                               onChange(addressFilter("img") with the entry,
//                               Delivery queue|latest); prints "ready", then at
//                               the DELETE of "img" one line {"stamps": {"REVISION":
//                               NS, ...}, "bytes": B, "events": E, "skipped": S,
//                               "checksum": C, "shared": H}: every overwrite
//                               received, each read whole through its ValueView
//                               before it is stamped (every byte of the image,
//                               field 1, in a checksum: the sum of its
//                               little-endian 64-bit words modulo 2**64, as the
//                               Java watcher's; no copy on the server's host,
//                               where the value is lent by shared memory), the
//                               image bytes, the events received (add and delete
//                               too), the changes a latest watch skipped, the sum
//                               of the overwrites' checksums and how many of them
//                               came by shared memory
//
// CLOCK_MONOTONIC is shared by every process of a Linux machine, so the stamps
// compare with the other process's and with Python's time.perf_counter_ns.
#include <google/protobuf/wrappers.pb.h>

#include <algorithm>
#include <chrono>
#include <condition_variable>
#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <functional>
#include <iostream>
#include <map>
#include <mutex>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "cast/cast.h"

namespace {

using Clock = std::chrono::steady_clock;

std::int64_t nowNs() {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(Clock::now().time_since_epoch()).count();
}

std::string stampsJson(const std::map<std::uint64_t, std::int64_t>& stamps) {
  std::ostringstream out;
  out << "{";
  bool first = true;
  for (const auto& [revision, ns] : stamps) {
    if (!first) out << ", ";
    first = false;
    out << "\"" << revision << "\": " << ns;
  }
  out << "}";
  return out.str();
}

google::protobuf::BytesValue value100() {
  google::protobuf::BytesValue v;
  v.set_value(std::string(100, 'x'));
  return v;
}

int addMode(cast::Component& c, long n, long warm) {
  const auto value = value100();
  // Ids made up front, as the Python benchmark does, so only the call is timed.
  std::vector<std::string> ids;
  ids.reserve(static_cast<std::size_t>(warm + n));
  for (long i = 0; i < warm + n; ++i) ids.push_back(c.componentId() + "-" + std::to_string(i));
  for (long i = 0; i < warm; ++i) c.add(ids[static_cast<std::size_t>(i)], value);
  const auto start = Clock::now();
  for (long i = warm; i < warm + n; ++i) c.add(ids[static_cast<std::size_t>(i)], value);
  const double seconds = std::chrono::duration<double>(Clock::now() - start).count();
  std::cout << "{\"calls\": " << n << ", \"seconds\": " << seconds << ", \"per_s\": " << n / seconds << "}"
            << std::endl;
  return 0;
}

int blocksMode(cast::Component& c, long warm) {
  const auto value = value100();
  long next = 0;
  auto id = [&] { return c.componentId() + "-" + std::to_string(next++); };
  for (long i = 0; i < warm; ++i) c.add(id(), value);
  std::cout << "ready" << std::endl;
  std::string line;
  while (std::getline(std::cin, line)) {
    char* rest = nullptr;
    const long b = std::strtol(line.c_str(), &rest, 10);
    const long w = std::strtol(rest, nullptr, 10);  // 0 when the line has no second number
    for (long i = 0; i < w; ++i) c.add(id(), value);
    // Ids made before the clock starts, so only the calls are timed.
    std::vector<std::string> ids;
    ids.reserve(static_cast<std::size_t>(b));
    for (long i = 0; i < b; ++i) ids.push_back(id());
    const auto start = Clock::now();
    for (const auto& entryId : ids) c.add(entryId, value);
    std::cout << std::chrono::duration<double>(Clock::now() - start).count() << std::endl;
  }
  return 0;
}

int watchMode(cast::Component& c, long n) {
  std::mutex mu;
  std::condition_variable done;
  std::map<std::uint64_t, std::int64_t> stamps;
  c.onChange(cast::addressFilter("lat"), [&](const cast::WorkingMemoryChange& change) {
    const std::int64_t t = nowNs();
    std::lock_guard<std::mutex> lock(mu);
    stamps[change.revision()] = t;
    if (static_cast<long>(stamps.size()) >= n) done.notify_all();
  });
  std::cout << "ready" << std::endl;
  std::unique_lock<std::mutex> lock(mu);
  done.wait_for(lock, std::chrono::seconds(120), [&] { return static_cast<long>(stamps.size()) >= n; });
  std::cout << stampsJson(stamps) << std::endl;
  return 0;
}

// Turns (bench/turns.py): of `sides` writers that share the machine, side `turn` (1..sides) writes in the
// seconds of CLOCK_MONOTONIC whose number modulo `sides` is turn - 1, each from kTurnSkipNs on, so that the
// side before has been read. Turn 0: no turn, write at any time.
constexpr std::int64_t kSecondNs = 1'000'000'000, kTurnSkipNs = 70'000'000;

struct Turn {
  int turn = 0, sides = 2;
};

// The first moment at or after `ns` in the turn's writing time (bench.turns.next_start).
std::int64_t turnStart(const Turn& t, std::int64_t ns) {
  if (t.turn == 0) return ns;
  const std::int64_t second = ns / kSecondNs, mine = t.turn - 1;
  if (second % t.sides == mine) return ns % kSecondNs >= kTurnSkipNs ? ns : second * kSecondNs + kTurnSkipNs;
  const std::int64_t ahead = ((mine - second % t.sides) % t.sides + t.sides) % t.sides;
  return (second + ahead) * kSecondNs + kTurnSkipNs;
}

// Sleeps until the turn's writing time; true if it slept (a paced schedule starts again from now).
bool waitForTurn(const Turn& t) {
  const std::int64_t now = nowNs(), begin = turnStart(t, now);
  if (begin == now) return false;
  std::this_thread::sleep_until(Clock::time_point(std::chrono::nanoseconds(begin)));
  return true;
}

int writeMode(cast::Component& c, long n, long gapMs, long warm, const Turn& turn) {
  const auto value = value100();
  std::map<std::uint64_t, std::int64_t> sent;
  c.add("lat", value);
  for (long i = 0; i < warm; ++i) {
    waitForTurn(turn);
    c.overwrite("lat", value);
  }
  for (long i = 0; i < n - 1; ++i) {
    std::this_thread::sleep_for(std::chrono::milliseconds(gapMs));
    waitForTurn(turn);
    const std::int64_t t0 = nowNs();
    sent[c.overwrite("lat", value).revision] = t0;
  }
  std::cout << stampsJson(sent) << std::endl;
  c.deleteEntry("lat");  // so that another run on this server can add it again
  return 0;
}

// How long image-write waits after its back-to-back warm-up: the watchers take what is still queued for
// them (and a JVM's compilers finish what the burst gave them) before the first measured overwrite
// (bench.peer_fanout.SETTLE_S for the peers).
constexpr auto kSettle = std::chrono::milliseconds(300);

// image-write's warm-up: `count` values of `size` bytes, back to back in bursts of `burst` (0: one burst), with
// `pauseUs` between bursts, so that no watcher falls a history's length behind before the measured part.
struct WarmUp {
  long count = 0, size = 0, burst = 0, pauseUs = 0;
};

int imageWriteMode(cast::Component& c, long size, long n, long gapUs, const WarmUp& warm, long cold, const Turn& turn) {
  // Value k (0, 1: SIZE bytes; 2, 3: WARM_SIZE bytes) is bytes of 1s (k even) or of 2s (k odd).
  auto byteOf = [](std::size_t k) { return static_cast<std::byte>(k % 2 + 1); };  // value k's every byte
  auto bytesOf = [&](std::size_t k) { return static_cast<std::size_t>(std::max(0L, k < 2 ? size : warm.size)); };
  const google::protobuf::BytesValue noBytes;  // what a loan of its `value` adds its bytes to
  std::map<std::uint64_t, std::int64_t> sent;
  long written = 0;  // the values alternate 1s, 2s over every overwrite, the warm-up's too
  // `count` overwrites with values base, base + 1, the i-th started at start + i * gap (an absolute
  // schedule, so the rate holds whatever each overwrite took; 0: back to back), each stamped just before it.
  // With a turn, one that would fall outside it waits for the turn's next start, and the schedule starts again.
  auto overwrite = [&](long count, long gap, std::size_t base, const Turn& inTurn) {
    auto start = Clock::now();
    for (long i = 0, step = 0; i < count; ++i, ++written, ++step) {
      if (gap > 0) std::this_thread::sleep_until(start + std::chrono::microseconds(gap * step));
      if (waitForTurn(inTurn)) {
        start = Clock::now();
        step = 0;
      }
      // Each frame is made just before its stamp, as the peers' publisher makes its payload
      // (bench.peer_fanout.drive): its bytes written in place, into a loan of the BytesValue's `value` (on
      // the server's host, the staging area the server copies it from, so the write copies nothing after the
      // stamp), so that, like a camera driver's fresh frame, it is in the cache when it is published rather
      // than where 66 ms of other frames left it.
      const std::size_t k = base + static_cast<std::size_t>(written) % 2;
      cast::Loan loan = c.loan(noBytes, "value", bytesOf(k));
      cast::MutableByteSpan bytes = loan.buffer();
      std::fill(bytes.begin(), bytes.end(), byteOf(k));
      const std::int64_t t0 = nowNs();
      sent[c.overwrite("img", std::move(loan)).revision] = t0;
    }
  };
  google::protobuf::BytesValue first;
  first.set_value(std::string(bytesOf(0), static_cast<char>(byteOf(0))));
  c.add("img", first);
  overwrite(cold, gapUs, 0, Turn{});  // the first seconds, every reader cold
  if (warm.count > 0) {
    const long burst = warm.burst > 0 ? warm.burst : warm.count;
    for (long left = warm.count; left > 0; left -= burst) {
      overwrite(std::min(burst, left), 0, 2, Turn{});
      if (left > burst) std::this_thread::sleep_for(std::chrono::microseconds(warm.pauseUs));
    }
    std::this_thread::sleep_for(kSettle);
  }
  if (turn.turn != 0) {  // the other side warms up meanwhile: the measured part waits for the word
    std::cout << "warm" << std::endl;
    std::string go;
    std::getline(std::cin, go);
  }
  overwrite(n, gapUs, 0, turn);
  c.deleteEntry("img");  // the watchers' end mark; a later run adds it again
  std::cout << stampsJson(sent) << std::endl;
  return 0;
}

// The sum of `bytes`' little-endian 64-bit words modulo 2**64, a last
// partial word as its bytes (Bench.checksum in Java).
std::uint64_t wordSum(cast::ByteSpan bytes) {
  const std::size_t whole = bytes.size() / 8 * 8;
  std::uint64_t sum = 0;
  for (std::size_t i = 0; i < whole; i += 8) {
    std::uint64_t word;
    std::memcpy(&word, bytes.data() + i, sizeof word);
#if __BYTE_ORDER__ == __ORDER_BIG_ENDIAN__
    word = __builtin_bswap64(word);
#endif
    sum += word;
  }
  for (std::size_t i = whole; i < bytes.size(); ++i) sum += static_cast<std::uint8_t>(bytes[i]);
  return sum;
}

// What the component does when its change delivery stops (set by image-watch: end now, not at its timeout).
std::function<void()> onWatchFailed;

// The benchmark's component: an unmanaged one that tells image-watch when its watch failed.
class BenchComponent : public cast::UnmanagedComponent {
 public:
  void watchFailed(const cast::CastError& error) override {
    cast::UnmanagedComponent::watchFailed(error);
    if (onWatchFailed) onWatchFailed();
  }
};

int imageWatchMode(cast::Component& c, const std::string& delivery) {
  std::mutex mu;
  std::condition_variable done;
  bool ended = false;
  onWatchFailed = [&] {
    std::lock_guard<std::mutex> lock(mu);
    ended = true;
    done.notify_all();
  };
  std::map<std::uint64_t, std::int64_t> stamps;
  std::uint64_t bytes = 0, events = 0, skipped = 0, shared = 0, checksum = 0;
  cast::WatchOptions options;
  options.delivery = delivery == "latest" ? cast::Delivery::Latest : cast::Delivery::Queue;
  c.onChange(
      cast::addressFilter("img").withEntry(),
      [&](const cast::WorkingMemoryChange& change) {
        if (change.operation() == cast::Operation::Delete) {
          std::lock_guard<std::mutex> lock(mu);
          ++events;
          skipped += change.skipped();
          ended = true;
          done.notify_all();
          return;
        }
        // Every byte of the image read where it is, as a consumer of frames would, then the stamp.
        const cast::ValueView view = change.view();
        const cast::ByteSpan pixels = view.field(1);
        const std::uint64_t sum = wordSum(pixels);
        const std::int64_t t = nowNs();
        std::lock_guard<std::mutex> lock(mu);
        ++events;
        skipped += change.skipped();
        if (change.operation() == cast::Operation::Overwrite) {
          stamps[change.revision()] = t;
          bytes += pixels.size();
          checksum += sum;
          shared += view.shared() ? 1 : 0;
        }
      },
      options);
  std::cout << "ready" << std::endl;
  std::unique_lock<std::mutex> lock(mu);
  done.wait_for(lock, std::chrono::seconds(300), [&] { return ended; });
  std::cout << "{\"stamps\": " << stampsJson(stamps) << ", \"bytes\": " << bytes << ", \"events\": " << events
            << ", \"skipped\": " << skipped << ", \"checksum\": " << checksum << ", \"shared\": " << shared << "}"
            << std::endl;
  return 0;
}

int usage() {
  std::cerr << "usage: cast_bench add N | blocks WARM | watch N | write N GAP_MS [WARM [TURN SIDES]] | "
               "image-write SIZE N GAP_US [WARM WARM_SIZE [COLD [BURST PAUSE_US [TURN]]]] | "
               "image-watch queue|latest (with the CAST_* launch environment)\n";
  return 2;
}

}  // namespace

int main(int argc, char** argv) {
  if (argc < 3) return usage();
  const std::string mode = argv[1];
  const long n = std::strtol(argv[2], nullptr, 10);
  if (mode == "image-watch" && std::string(argv[2]) != "queue" && std::string(argv[2]) != "latest") return usage();
  if (mode != "image-watch" && n <= 0) return usage();
  if ((mode == "write" && argc < 4) || (mode == "image-write" && argc < 5)) return usage();
  if (mode == "image-write" && argc > 10 && std::string(argv[10]) != "0" && std::string(argv[10]) != "1" &&
      std::string(argv[10]) != "2")
    return usage();
  if (mode == "write" && argc > 5) {  // TURN SIDES: 1 <= TURN <= SIDES, or TURN 0 (none)
    const long turn = std::strtol(argv[5], nullptr, 10), sides = argc > 6 ? std::strtol(argv[6], nullptr, 10) : 2;
    if (turn < 0 || sides < 1 || turn > sides) return usage();
  }
  try {
    const auto contract = cast::LaunchContract::fromEnv();
    BenchComponent component;
    component.bind(contract.connect());
    int code;
    if (mode == "add") code = addMode(component, n, argc > 3 ? std::strtol(argv[3], nullptr, 10) : 200);
    else if (mode == "blocks") code = blocksMode(component, n);
    else if (mode == "watch") code = watchMode(component, n);
    else if (mode == "write")
      code = writeMode(component, n, std::strtol(argv[3], nullptr, 10),
                       argc > 4 ? std::strtol(argv[4], nullptr, 10) : 0,
                       Turn{argc > 5 ? static_cast<int>(std::strtol(argv[5], nullptr, 10)) : 0,
                            argc > 6 ? static_cast<int>(std::strtol(argv[6], nullptr, 10)) : 2});
    else if (mode == "image-write")
      code = imageWriteMode(component, n, std::strtol(argv[3], nullptr, 10), std::strtol(argv[4], nullptr, 10),
                            WarmUp{argc > 5 ? std::strtol(argv[5], nullptr, 10) : 0,
                                   argc > 6 ? std::strtol(argv[6], nullptr, 10) : n,
                                   argc > 8 ? std::strtol(argv[8], nullptr, 10) : 0,
                                   argc > 9 ? std::strtol(argv[9], nullptr, 10) : 0},
                            argc > 7 ? std::strtol(argv[7], nullptr, 10) : 0,
                            Turn{argc > 10 ? static_cast<int>(std::strtol(argv[10], nullptr, 10)) : 0, 2});
    else if (mode == "image-watch") code = imageWatchMode(component, argv[2]);
    else return usage();
    component.close();
    return code;
  } catch (const cast::CastError& e) {
    std::cerr << "cast_bench: " << e.name() << ": " << e.message() << std::endl;
    return 1;
  }
}
