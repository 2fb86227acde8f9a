#include "cast/log.h"

#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <ctime>
#include <mutex>

namespace cast {

namespace {

LogLevel thresholdFromEnv() {
  const char* v = std::getenv("CAST_LOG_LEVEL");
  if (v == nullptr) return LogLevel::Info;
  std::string s(v);
  if (s == "DEBUG") return LogLevel::Debug;
  if (s == "WARNING" || s == "WARN") return LogLevel::Warning;
  if (s == "ERROR") return LogLevel::Error;
  return LogLevel::Info;
}

const char* levelName(LogLevel level) {
  switch (level) {
    case LogLevel::Debug: return "DEBUG";
    case LogLevel::Info: return "INFO";
    case LogLevel::Warning: return "WARNING";
    case LogLevel::Error: return "ERROR";
  }
  return "?";
}

std::mutex& outputMutex() {
  static std::mutex mu;
  return mu;
}

}  // namespace

bool Logger::enabled(LogLevel level) const {
  static const LogLevel threshold = thresholdFromEnv();
  return static_cast<int>(level) >= static_cast<int>(threshold);
}

void Logger::log(LogLevel level, const std::string& message) const {
  if (!enabled(level)) return;
  const auto now = std::chrono::system_clock::now();
  const std::time_t secs = std::chrono::system_clock::to_time_t(now);
  const auto ms = std::chrono::duration_cast<std::chrono::milliseconds>(now.time_since_epoch()).count() % 1000;
  std::tm tm{};
  localtime_r(&secs, &tm);
  char stamp[32];
  std::strftime(stamp, sizeof stamp, "%Y-%m-%d %H:%M:%S", &tm);
  std::lock_guard<std::mutex> lock(outputMutex());
  std::fprintf(stderr, "%s,%03d %s %s: %s\n", stamp, static_cast<int>(ms), levelName(level), name_.c_str(),
               message.c_str());
  std::fflush(stderr);
}

}  // namespace cast
