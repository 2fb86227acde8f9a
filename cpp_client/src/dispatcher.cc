#include "dispatcher.h"

#include <poll.h>
#include <sys/eventfd.h>
#include <sys/timerfd.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstdint>
#include <exception>
#include <system_error>
#include <utility>

#include "cast/errors.h"

namespace cast::detail {

namespace {

constexpr short kReadable = POLLIN | POLLPRI | POLLERR | POLLHUP;
// How long the thread waits (for a call) while another thread reads a source.
constexpr int kBusyMs = 1;

int descriptor(int fd, const char* what) {
  if (fd < 0) throw std::system_error(errno, std::generic_category(), what);
  return fd;
}

void drainFd(int fd) {
  std::uint64_t n;
  while (::read(fd, &n, sizeof n) == static_cast<ssize_t>(sizeof n)) {
  }
}

void poke(int fd) {
  const std::uint64_t one = 1;
  const ssize_t written = ::write(fd, &one, sizeof one);
  (void)written;  // a full counter is a wake-up pending already
}

void setAlarm(int fd, std::chrono::milliseconds after) {
  itimerspec spec{};
  spec.it_value.tv_sec = static_cast<time_t>(after.count() / 1000);
  spec.it_value.tv_nsec = static_cast<long>(after.count() % 1000) * 1000000L;
  ::timerfd_settime(fd, 0, &spec, nullptr);
}

bool anyQueued(const std::array<std::deque<std::function<void()>>, 3>& queues) {
  return std::any_of(queues.begin(), queues.end(), [](const auto& q) { return !q.empty(); });
}

bool sameSource(const std::weak_ptr<EventSource>& a, const std::weak_ptr<EventSource>& b) {
  return !a.owner_before(b) && !b.owner_before(a);
}

// Appends the live sources to `order` and their descriptors to `fds`, in the same order; those ended
// or gone are forgotten. Called with the state's mutex held: what it locks is let go by the caller,
// after that mutex (a source's last holder ends it, which may queue a call).
void collect(std::vector<std::weak_ptr<EventSource>>& sources, std::vector<std::weak_ptr<EventSource>>& order,
             std::vector<pollfd>& fds, std::vector<std::shared_ptr<EventSource>>& held) {
  for (auto it = sources.begin(); it != sources.end();) {
    std::shared_ptr<EventSource> source = it->lock();
    const int fd = source ? source->sourceFd() : -1;
    if (source) held.push_back(std::move(source));
    if (fd < 0) {
      it = sources.erase(it);
      continue;
    }
    order.push_back(*it);
    fds.push_back(pollfd{fd, kReadable, 0});
    ++it;
  }
}

// Reads each source `fds` says is readable (fds[i + skip] is order[i]'s); false when another thread
// was reading one of them.
bool pumpReady(const std::vector<std::weak_ptr<EventSource>>& order, const std::vector<pollfd>& fds,
               std::size_t skip) {
  bool all = true;
  for (std::size_t i = 0; i < order.size(); ++i) {
    if (fds[i + skip].revents == 0) continue;
    std::shared_ptr<EventSource> source = order[i].lock();
    if (source && source->sourceFd() >= 0) all = source->pump() && all;  // not one that ended meanwhile
  }
  return all;
}

}  // namespace

Dispatcher::State::State(std::string name, std::size_t capacity)
    : log(std::move(name)),
      capacity(capacity),
      wakeFd(descriptor(::eventfd(0, EFD_NONBLOCK | EFD_CLOEXEC), "eventfd for the dispatcher")),
      alarmFd(descriptor(::timerfd_create(CLOCK_MONOTONIC, TFD_NONBLOCK | TFD_CLOEXEC), "timerfd for the dispatcher")),
      stopFd(descriptor(::eventfd(0, EFD_NONBLOCK | EFD_CLOEXEC), "eventfd for the dispatcher")) {}

Dispatcher::State::~State() {
  ::close(wakeFd);
  ::close(alarmFd);
  ::close(stopFd);
}

Dispatcher::Dispatcher(std::string name, std::size_t capacity)
    : state_(std::make_shared<State>("cast.dispatch." + name, capacity == 0 ? 1 : capacity)) {
  thread_ = std::thread([state = state_] { loop(state); });
  threadId_ = thread_.get_id();
}

Dispatcher::~Dispatcher() { stop(); }

void Dispatcher::submit(std::function<void()> fn, Priority priority, bool wait) {
  bool polling = false;
  {
    std::unique_lock<std::mutex> lock(state_->mu);
    if (wait && !onThread()) {
      state_->idle.wait(lock, [this] { return state_->pending < state_->capacity || state_->stopping; });
    }
    if (state_->stopping) return;
    state_->queues.at(static_cast<std::size_t>(priority)).push_back(std::move(fn));
    ++state_->pending;
    polling = state_->polling;
  }
  if (polling) poke(state_->wakeFd);
  state_->wake.notify_one();
}

void Dispatcher::attach(std::weak_ptr<EventSource> source) {
  bool polling = false;
  {
    std::lock_guard<std::mutex> lock(state_->mu);
    if (state_->stopping) return;
    auto& sources = state_->sources;
    if (std::none_of(sources.begin(), sources.end(), [&](const auto& s) { return sameSource(s, source); })) {
      sources.push_back(std::move(source));
    }
    if (!state_->standbyStarted) {
      state_->standbyStarted = true;
      standby_ = std::thread([state = state_] { standBy(state); });
    }
    polling = state_->polling;
  }
  if (polling) poke(state_->wakeFd);
  state_->wake.notify_one();  // a thread waiting without sources waits on them from now on
}

void Dispatcher::loop(const std::shared_ptr<State>& s) {
  bool readNow = false;  // every source ready was read just now: no second look before the call
  for (;;) {
    std::function<void()> fn;
    bool sources = false;
    bool queued = false;
    {
      std::unique_lock<std::mutex> lock(s->mu);
      s->wake.wait(lock, [&] { return anyQueued(s->queues) || s->stopping || !s->sources.empty(); });
      sources = !s->sources.empty();
      queued = anyQueued(s->queues);
      if (!queued && s->stopping) break;  // stopping and nothing left to run
    }
    if (sources) {
      if (!queued) {
        readSources(*s, true);
        readNow = true;
        continue;
      }
      if (!readNow) readSources(*s, false);  // what came first, so that a higher priority's event goes first
      readNow = false;
    }
    {
      std::lock_guard<std::mutex> lock(s->mu);
      auto next = std::find_if(s->queues.begin(), s->queues.end(), [](const auto& q) { return !q.empty(); });
      fn = std::move(next->front());  // only this thread takes calls: the one seen is still there
      next->pop_front();
    }
    runOne(*s, fn);
  }
  std::lock_guard<std::mutex> lock(s->mu);
  s->finished = true;
  s->idle.notify_all();
}

void Dispatcher::readSources(State& s, bool wait) {
  std::vector<std::weak_ptr<EventSource>> order;
  std::vector<pollfd> fds{pollfd{s.wakeFd, POLLIN, 0}};
  std::vector<std::shared_ptr<EventSource>> held;  // let go after the mutex, not while waiting
  {
    std::lock_guard<std::mutex> lock(s.mu);
    collect(s.sources, order, fds, held);
    if (wait && (anyQueued(s.queues) || s.stopping)) wait = false;
    // Full: what the sources have waits for room (and the server for the socket).
    if (!wait && s.pending >= s.capacity) return;
    s.polling = wait;
  }
  held.clear();
  if (order.empty() && !wait) return;
  const int ready = ::poll(fds.data(), fds.size(), wait ? -1 : 0);
  {
    std::lock_guard<std::mutex> lock(s.mu);
    s.polling = false;
  }
  if (ready <= 0) return;
  if (fds[0].revents != 0) drainFd(s.wakeFd);
  if (!pumpReady(order, fds, 1)) {
    // Another thread is reading one (and queues what it reads here): its socket stays readable until it
    // has, so wait for a call or a moment rather than spin on it.
    {
      std::lock_guard<std::mutex> lock(s.mu);
      if (anyQueued(s.queues) || s.stopping) return;
      s.polling = true;
    }
    pollfd wake{s.wakeFd, POLLIN, 0};
    ::poll(&wake, 1, kBusyMs);
    {
      std::lock_guard<std::mutex> lock(s.mu);
      s.polling = false;
    }
    drainFd(s.wakeFd);
  }
}

void Dispatcher::runOne(State& s, std::function<void()>& fn) {
  s.calling.store(true);
  const bool standby = s.standbyStarted.load();
  // The standby sleeps on the alarm: it wakes only for a callback that runs kStandby, never at a start.
  if (standby) setAlarm(s.alarmFd, kStandby);
  try {
    fn();
  } catch (const CastError& e) {
    s.log.error(std::string("callback failed: ") + e.name() + ": " + e.message());
  } catch (const std::exception& e) {
    s.log.error(std::string("callback failed: ") + e.what());
  } catch (...) {
    s.log.error("callback failed with a non-standard exception");
  }
  fn = nullptr;  // destroy what the callback captured before reporting idle
  s.calling.store(false);
  if (standby) setAlarm(s.alarmFd, std::chrono::milliseconds(0));
  std::lock_guard<std::mutex> lock(s.mu);
  --s.pending;
  s.idle.notify_all();  // room for a waiting submit, or idle for drain()
}

void Dispatcher::standBy(const std::shared_ptr<State>& s) {
  for (;;) {
    pollfd waits[2] = {pollfd{s->alarmFd, POLLIN, 0}, pollfd{s->stopFd, POLLIN, 0}};
    if (::poll(waits, 2, -1) < 0 && errno != EINTR) return;
    if (waits[1].revents != 0) return;
    if (waits[0].revents != 0) drainFd(s->alarmFd);
    // A callback ran kStandby: read the sources in its place for as long as callbacks run.
    while (s->calling.load()) {
      std::vector<std::weak_ptr<EventSource>> order;
      std::vector<pollfd> fds{pollfd{s->stopFd, POLLIN, 0}};
      std::vector<std::shared_ptr<EventSource>> held;
      bool room = false;
      {
        std::lock_guard<std::mutex> lock(s->mu);
        if (s->stopping) return;
        collect(s->sources, order, fds, held);
        room = s->pending < s->capacity;
      }
      held.clear();
      if (!room || order.empty()) fds.resize(1);  // nothing to read now: look again in a moment
      const int ready = ::poll(fds.data(), fds.size(), static_cast<int>(kStandby.count()));
      if (ready > 0 && fds[0].revents != 0) return;
      if (ready > 0 && fds.size() > 1) pumpReady(order, fds, 1);
    }
  }
}

bool Dispatcher::awaitRoom(std::chrono::milliseconds timeout) {
  std::unique_lock<std::mutex> lock(state_->mu);
  state_->idle.wait_for(lock, timeout, [this] { return state_->pending < state_->capacity || state_->stopping; });
  return state_->pending < state_->capacity || state_->stopping;
}

bool Dispatcher::drain(std::chrono::milliseconds timeout) {
  if (onThread()) return false;
  std::unique_lock<std::mutex> lock(state_->mu);
  return state_->idle.wait_for(lock, timeout, [this] { return state_->pending == 0 || state_->finished; });
}

void Dispatcher::stop(std::chrono::milliseconds timeout) {
  bool polling = false;
  {
    std::lock_guard<std::mutex> lock(state_->mu);
    state_->stopping = true;
    polling = state_->polling;
  }
  if (polling) poke(state_->wakeFd);
  poke(state_->stopFd);  // the standby thread ends
  state_->wake.notify_all();
  state_->idle.notify_all();  // a submit waiting for room gives up
  if (standby_.joinable()) standby_.join();
  if (!thread_.joinable()) return;
  if (onThread()) {
    // stop() from a callback: the thread ends after this callback returns.
    thread_.detach();
    return;
  }
  {
    std::unique_lock<std::mutex> lock(state_->mu);
    if (!state_->idle.wait_for(lock, timeout, [this] { return state_->finished; })) {
      state_->log.error("a callback was still running " + std::to_string(timeout.count()) +
                        " ms after stop; leaving the dispatcher thread behind");
      thread_.detach();
      return;
    }
  }
  thread_.join();
}

}  // namespace cast::detail
