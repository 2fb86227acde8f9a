// Minimal logging to stderr, one line per message, safe from any thread.
// Level from CAST_LOG_LEVEL (DEBUG, INFO, WARNING, ERROR; default INFO), as
// for Python components, so the orchestrator's logs read the same.
#pragma once

#include <sstream>
#include <string>

namespace cast {

enum class LogLevel { Debug = 10, Info = 20, Warning = 30, Error = 40 };

class Logger {
 public:
  explicit Logger(std::string name) : name_(std::move(name)) {}
  const std::string& name() const { return name_; }
  bool enabled(LogLevel level) const;
  void log(LogLevel level, const std::string& message) const;
  void debug(const std::string& message) const { log(LogLevel::Debug, message); }
  void info(const std::string& message) const { log(LogLevel::Info, message); }
  void warning(const std::string& message) const { log(LogLevel::Warning, message); }
  void error(const std::string& message) const { log(LogLevel::Error, message); }

 private:
  std::string name_;
};

}  // namespace cast
