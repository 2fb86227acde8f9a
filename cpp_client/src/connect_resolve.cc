#include "connect_resolve.h"

#include <signal.h>
#include <unistd.h>

#include <cerrno>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <stdexcept>

#include "cast/credentials.h"
#include "json_value.h"

namespace cast::detail {

namespace {

std::string envOr(const std::map<std::string, std::string>& env, const char* name) {
  auto it = env.find(name);
  return it == env.end() ? std::string() : it->second;
}

// Whitespace stripped from both ends, as Python's bytes.strip() does.
std::string trim(const std::string& text) {
  const char* ws = " \t\r\n\v\f";
  const auto first = text.find_first_not_of(ws);
  if (first == std::string::npos) return "";
  return text.substr(first, text.find_last_not_of(ws) - first + 1);
}

std::optional<std::string> readFile(const std::string& path) {
  // A directory opens as a stream on Linux and reads as empty: it is a file that cannot be read.
  std::error_code ec;
  if (std::filesystem::is_directory(path, ec)) return std::nullopt;
  std::ifstream in(path, std::ios::binary);
  if (!in) return std::nullopt;
  std::ostringstream text;
  text << in.rdbuf();
  return text.str();
}

bool processAlive(long pid) {
  if (pid <= 0) return false;
  // Signal 0 only checks: EPERM means it exists but belongs to someone else.
  return ::kill(static_cast<pid_t>(pid), 0) == 0 || errno == EPERM;
}

// What <runtime dir>/system.json says, when a running `cast run` wrote it.
struct Recorded {
  bool usable = false;
  std::string path;
  std::string why;  // why it cannot be used
  std::string endpoint;
  std::string firstSa;  // the first SA of the first server
  std::optional<ClientTls> tls;
};

std::string stringMember(const JsonValue& object, const char* key) {
  const JsonValue* v = object.find(key);
  return v != nullptr && v->isString() ? v->string : std::string();
}

Recorded readSystemJson(const std::string& dir) {
  Recorded r;
  r.path = dir + "/system.json";
  auto text = readFile(r.path);
  if (!text) {
    r.why = "there is no " + r.path + " (a running `cast run` writes it)";
    return r;
  }
  JsonValue state;
  try {
    state = parseJson(*text);
  } catch (const std::invalid_argument& e) {
    r.why = r.path + " is not JSON (" + e.what() + ")";
    return r;
  }
  const JsonValue* pid = state.find("pid");
  if (pid == nullptr || pid->kind != JsonValue::Kind::Number) {
    r.why = r.path + " names no process (\"pid\"), so it was not written by `cast run`";
    return r;
  }
  const long number = static_cast<long>(pid->number);
  if (!processAlive(number)) {
    // A `cast run` that was killed leaves its system.json behind.
    r.why = r.path + " was written by process " + std::to_string(number) + ", which is no longer running";
    return r;
  }
  r.endpoint = stringMember(state, "endpoint");
  if (r.endpoint.empty()) {
    r.why = r.path + " has no \"endpoint\"";
    return r;
  }
  if (const JsonValue* servers = state.find("servers"); servers != nullptr && !servers->members.empty()) {
    if (const JsonValue* sas = servers->members.front().second.find("subarchitectures");
        sas != nullptr && !sas->items.empty() && sas->items.front().isString()) {
      r.firstSa = sas->items.front().string;
    }
  }
  if (const JsonValue* tls = state.find("tls"); tls != nullptr && tls->isObject()) {
    ClientTls recorded{stringMember(*tls, "ca"), stringMember(*tls, "cert"), stringMember(*tls, "key"), ""};
    if (!recorded.ca.empty()) r.tls = recorded;
  }
  r.usable = true;
  return r;
}

// The system's secret, and where it came from; nullopt if there is none.
std::optional<std::pair<std::string, std::string>> findSecret(const std::map<std::string, std::string>& env,
                                                              const std::string& dir) {
  if (auto secret = envOr(env, "CAST_SECRET"); !secret.empty()) return std::make_pair(secret, std::string("CAST_SECRET"));
  if (auto path = envOr(env, "CAST_SECRET_FILE"); !path.empty()) {
    auto text = readFile(path);
    if (!text || trim(*text).empty()) {
      throw InvalidArgumentError("CAST_SECRET_FILE names " + path + ", which " +
                                 (text ? "is empty" : "cannot be read") +
                                 ": point it at the system's secret file, or unset it");
    }
    return std::make_pair(trim(*text), "the file " + path + " (CAST_SECRET_FILE)");
  }
  const std::string path = dir + "/secret";
  if (auto text = readFile(path); text && !trim(*text).empty()) return std::make_pair(trim(*text), path);
  return std::nullopt;
}

// The identity a given token states; UnauthenticatedError if it is no CAST
// token (the server would refuse it so), InvalidArgumentError if it
// contradicts the options.
Identity claimsOf(const std::string& token, const std::string& source, const ConnectOptions& options) {
  auto claimed = peekToken(token);
  if (!claimed) {
    const bool oldFormat = token.find('.') != std::string::npos && token.find('.') == token.rfind('.');
    throw UnauthenticatedError("the token from " + source + " is not a CAST token" +
                               (oldFormat ? " (it has the format before JWTs)" : " (a JWT with the claims c, s, p)") +
                               ": get one with `cast token COMPONENT_ID --sa SA`");
  }
  if (!options.componentId.empty() && options.componentId != claimed->componentId) {
    throw InvalidArgumentError("ConnectOptions::componentId is '" + options.componentId + "' but the token from " +
                               source + " is for '" + claimed->componentId +
                               "': a token decides the identity; drop componentId, or give a token for it");
  }
  if (!options.subarchitecture.empty() && options.subarchitecture != claimed->subarchitecture) {
    throw InvalidArgumentError("ConnectOptions::subarchitecture is '" + options.subarchitecture +
                               "' but the token from " + source + " is for '" + claimed->subarchitecture +
                               "': a token decides the identity; drop subarchitecture, or give a token for it");
  }
  return *claimed;
}

}  // namespace

std::string defaultScriptId() {
  char host[256] = {};
  if (::gethostname(host, sizeof host - 1) != 0 || host[0] == '\0') std::snprintf(host, sizeof host, "localhost");
  return "script-" + std::string(host) + "-" + std::to_string(::getpid());
}

std::string readTokenFile(const std::string& path) {
  auto text = readFile(path);
  if (!text || trim(*text).empty()) {
    throw InvalidArgumentError("CAST_TOKEN_FILE names " + path + ", which " + (text ? "is empty" : "cannot be read") +
                               ": point it at a token file (`cast run` renews one per component), or unset it");
  }
  return trim(*text);
}

ConnectPlan resolveConnect(const ConnectOptions& options, const std::map<std::string, std::string>& env,
                           std::int64_t now) {
  std::string dir = options.runtimeDir;
  if (dir.empty()) dir = envOr(env, "CAST_RUNTIME_DIR");
  if (dir.empty()) dir = ".cast";
  // Read at most once, and only when an earlier source has nothing.
  std::optional<Recorded> recorded;
  auto system = [&]() -> const Recorded& {
    if (!recorded) recorded = readSystemJson(dir);
    return *recorded;
  };

  ConnectPlan plan;
  if (!options.endpoint.empty()) {
    plan.endpoint = options.endpoint;
    plan.endpointSource = "ConnectOptions::endpoint";
  } else if (auto endpoint = envOr(env, "CAST_ENDPOINT"); !endpoint.empty()) {
    plan.endpoint = endpoint;
    plan.endpointSource = "CAST_ENDPOINT";
  } else if (system().usable) {
    plan.endpoint = system().endpoint;
    plan.endpointSource = system().path;
  } else {
    throw NotFoundError("no CAST system to connect to: " + system().why +
                               "; start one with `cast run CONFIG`, give ConnectOptions::runtimeDir (or "
                               "CAST_RUNTIME_DIR) where it runs, or give ConnectOptions::endpoint (or CAST_ENDPOINT)");
  }

  std::string source;
  if (!options.token.empty()) {
    plan.token = options.token;
    source = "ConnectOptions::token";
  } else if (auto path = envOr(env, "CAST_TOKEN_FILE"); !path.empty()) {
    plan.token = readTokenFile(path);
    plan.tokenFile = path;
    source = "the file " + path + " (CAST_TOKEN_FILE)";
  } else if (auto token = envOr(env, "CAST_TOKEN"); !token.empty()) {
    plan.token = token;
    source = "CAST_TOKEN";
  }

  if (!plan.token.empty()) {
    plan.identity = claimsOf(plan.token, source, options);
  } else {
    auto secret = findSecret(env, dir);
    if (!secret) {
      throw NotFoundError("no token and no secret to mint one: give ConnectOptions::token, set CAST_TOKEN or "
                                 "CAST_TOKEN_FILE (`cast token` prints a token), or set CAST_SECRET or "
                                 "CAST_SECRET_FILE to the system's secret (" + dir +
                                 "/secret, which a running `cast run` writes, does not exist)");
    }
    Identity identity{options.componentId.empty() ? defaultScriptId() : options.componentId, options.subarchitecture,
                      true};  // whoever holds the secret could mint any token: it is trusted
    if (identity.subarchitecture.empty()) {
      if (!system().usable || system().firstSa.empty()) {
        throw InvalidArgumentError("which subarchitecture is this program's own? give ConnectOptions::subarchitecture (" +
                                   (system().usable ? system().path + " lists no subarchitecture" : system().why) +
                                   ", so it cannot be taken from there)");
      }
      identity.subarchitecture = system().firstSa;
    }
    try {
      plan.token = mintToken(secret->first, identity, now);
    } catch (const InvalidArgumentError& e) {
      throw InvalidArgumentError("the secret from " + secret->second + ": " + e.message());
    }
    plan.identity = identity;
  }

  if (options.tls) {
    if (options.tls->ca.empty()) {
      throw InvalidArgumentError("ConnectOptions::tls has no ca: give the PEM file of the CA that signed the servers' "
                                 "certificates (or no tls, for plaintext)");
    }
    if (options.tls->cert.empty() != options.tls->key.empty()) {
      throw InvalidArgumentError("ConnectOptions::tls: give both cert and key, or neither");
    }
    plan.tls = options.tls;
  } else if (auto fromEnv = ClientTls::fromEnv(env)) {
    plan.tls = fromEnv;
  } else if (system().usable && system().tls) {
    plan.tls = system().tls;
  }
  return plan;
}

}  // namespace cast::detail
