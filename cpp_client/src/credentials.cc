// Credentials (cast/credentials.h): tokens fixed or renewed through a file,
// reading and minting JWTs, TLS settings and the channel credentials built
// from them. Mirrors the Python client's client/credentials.py.
#include "cast/credentials.h"

#include <google/protobuf/struct.pb.h>
#include <google/protobuf/util/json_util.h>
#include <grpcpp/grpcpp.h>
#include <openssl/evp.h>
#include <openssl/hmac.h>
#include <sys/stat.h>

#include <cstdio>
#include <fstream>
#include <iterator>
#include <sstream>

#include "cast/errors.h"
#include "grpc_server.h"
#include "jwt.h"

namespace cast {

namespace {

// The header every CAST token has, already encoded: it never changes.
const char* const kHeader = "eyJhbGciOiJIUzI1NiIsInR5cCI6IkpXVCJ9";  // {"alg":"HS256","typ":"JWT"}
constexpr std::size_t kMinSecret = 32;

// A JSON string literal, escaped as Python's json.dumps escapes ASCII, so a
// token minted here for an ASCII id is byte for byte the one `cast token` mints.
std::string jsonString(const std::string& text) {
  std::string out = "\"";
  for (unsigned char ch : text) {
    switch (ch) {
      case '"': out += "\\\""; break;
      case '\\': out += "\\\\"; break;
      case '\n': out += "\\n"; break;
      case '\r': out += "\\r"; break;
      case '\t': out += "\\t"; break;
      case '\b': out += "\\b"; break;
      case '\f': out += "\\f"; break;
      default:
        if (ch < 0x20) {
          char buf[8];
          std::snprintf(buf, sizeof buf, "\\u%04x", ch);
          out += buf;
        } else {
          out.push_back(static_cast<char>(ch));  // UTF-8 passes through: valid JSON
        }
    }
  }
  return out + "\"";
}

}  // namespace

// ------------------------------------------------------------ TLS

std::optional<ClientTls> ClientTls::fromEnv(const std::map<std::string, std::string>& env) {
  auto get = [&](const char* name) {
    auto it = env.find(name);
    return it == env.end() ? std::string() : it->second;
  };
  ClientTls tls{get("CAST_TLS_CA"), get("CAST_TLS_CERT"), get("CAST_TLS_KEY"), get("CAST_TLS_SERVER_NAME")};
  if (tls.ca.empty()) {
    if (!tls.cert.empty() || !tls.key.empty()) {
      throw InvalidArgumentError("CAST_TLS_CERT/CAST_TLS_KEY given without CAST_TLS_CA: set the CA too");
    }
    return std::nullopt;
  }
  if (tls.cert.empty() != tls.key.empty()) {
    throw InvalidArgumentError("set both CAST_TLS_CERT and CAST_TLS_KEY, or neither");
  }
  return tls;
}

namespace detail {

namespace {

std::string readTlsFile(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) throw InvalidArgumentError("cannot read a TLS file (CAST_TLS_CA/CERT/KEY): " + path);
  std::ostringstream text;
  text << in.rdbuf();
  return text.str();
}

}  // namespace

std::shared_ptr<grpc::ChannelCredentials> channelCredentials(const std::optional<ClientTls>& tls,
                                                             grpc::ChannelArguments& args) {
  if (!tls) return grpc::InsecureChannelCredentials();
  grpc::SslCredentialsOptions ssl;
  ssl.pem_root_certs = readTlsFile(tls->ca);
  if (!tls->cert.empty()) {
    ssl.pem_cert_chain = readTlsFile(tls->cert);
    ssl.pem_private_key = readTlsFile(tls->key);
  }
  if (!tls->serverName.empty()) args.SetSslTargetNameOverride(tls->serverName);
  return grpc::SslCredentials(ssl);
}

}  // namespace detail

// ------------------------------------------------------------ tokens from a file

TokenSource::TokenSource(std::string token, std::string path, std::chrono::milliseconds checkInterval)
    : token_(std::move(token)), path_(std::move(path)), interval_(checkInterval) {
  if (!path_.empty()) reload(true);
}

void TokenSource::reload(bool force) {
  // Called with mu_ held.
  const auto now = std::chrono::steady_clock::now();
  if (!force && now - checked_ < interval_) return;
  checked_ = now;
  struct stat st {};
  if (::stat(path_.c_str(), &st) != 0) return;  // keep the last token: the file may be being replaced
  const std::pair<long long, long long> stamp{
      static_cast<long long>(st.st_mtim.tv_sec) * 1000000000LL + st.st_mtim.tv_nsec,
      static_cast<long long>(st.st_size)};
  if (stamp == stamp_) return;
  std::ifstream in(path_);
  std::string text((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  const auto first = text.find_first_not_of(" \t\r\n");
  const auto last = text.find_last_not_of(" \t\r\n");
  if (first != std::string::npos) token_ = text.substr(first, last - first + 1);
  stamp_ = stamp;
}

std::string TokenSource::token() {
  std::lock_guard<std::mutex> lock(mu_);
  if (!path_.empty()) reload(false);
  return token_;
}

bool TokenSource::refresh() {
  if (path_.empty()) return false;
  std::lock_guard<std::mutex> lock(mu_);
  const std::string before = token_;
  reload(true);
  return token_ != before;
}

// ------------------------------------------------------------ JWTs

namespace detail {

std::string base64UrlEncode(const std::string& bytes) {
  static const char* const alphabet = "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789-_";
  std::string out;
  unsigned value = 0;
  int bits = 0;
  for (unsigned char ch : bytes) {
    value = (value << 8) | ch;
    bits += 8;
    while (bits >= 6) {
      bits -= 6;
      out.push_back(alphabet[(value >> bits) & 0x3fu]);
    }
  }
  if (bits > 0) out.push_back(alphabet[(value << (6 - bits)) & 0x3fu]);
  return out;
}

std::optional<std::string> base64UrlDecode(const std::string& text) {
  std::string out;
  unsigned value = 0;
  int bits = 0;
  for (char ch : text) {
    int d;
    if (ch >= 'A' && ch <= 'Z') d = ch - 'A';
    else if (ch >= 'a' && ch <= 'z') d = ch - 'a' + 26;
    else if (ch >= '0' && ch <= '9') d = ch - '0' + 52;
    else if (ch == '-') d = 62;
    else if (ch == '_') d = 63;
    else if (ch == '=') break;
    else return std::nullopt;
    value = (value << 6) | static_cast<unsigned>(d);
    bits += 6;
    if (bits >= 8) {
      bits -= 8;
      out.push_back(static_cast<char>((value >> bits) & 0xffu));
    }
  }
  return out;
}

std::string signHs256(const std::string& signingInput, const std::string& secret) {
  unsigned char mac[EVP_MAX_MD_SIZE];
  unsigned int length = 0;
  if (HMAC(EVP_sha256(), secret.data(), static_cast<int>(secret.size()),
           reinterpret_cast<const unsigned char*>(signingInput.data()), signingInput.size(), mac, &length) == nullptr) {
    throw InternalError("HMAC-SHA256 failed in OpenSSL: cannot sign the token");
  }
  return base64UrlEncode(std::string(reinterpret_cast<const char*>(mac), length));
}

}  // namespace detail

std::optional<Identity> peekToken(const std::string& token) {
  // A JWT has three parts; the claims are the middle one.
  const auto first = token.find('.');
  if (first == std::string::npos) return std::nullopt;
  const auto second = token.find('.', first + 1);
  if (second == std::string::npos || token.find('.', second + 1) != std::string::npos) return std::nullopt;
  auto payload = detail::base64UrlDecode(token.substr(first + 1, second - first - 1));
  if (!payload) return std::nullopt;
  google::protobuf::Struct claims;
  if (!google::protobuf::util::JsonStringToMessage(*payload, &claims).ok()) return std::nullopt;
  const auto& f = claims.fields();
  auto c = f.find("c");
  auto s = f.find("s");
  auto p = f.find("p");
  if (c == f.end() || s == f.end() || p == f.end()) return std::nullopt;
  if (c->second.kind_case() != google::protobuf::Value::kStringValue ||
      s->second.kind_case() != google::protobuf::Value::kStringValue ||
      p->second.kind_case() != google::protobuf::Value::kBoolValue) {
    return std::nullopt;
  }
  return Identity{c->second.string_value(), s->second.string_value(), p->second.bool_value()};
}

std::string mintToken(const std::string& secret, const Identity& identity, std::int64_t issuedAt) {
  if (secret.size() < kMinSecret) {
    throw InvalidArgumentError("the token secret is " + std::to_string(secret.size()) +
                               " bytes, shorter than 32: HS256 needs at least 32 bytes; use the secret of the "
                               "running system (`cast run` writes it to <runtime dir>/secret)");
  }
  // The claims in the order cast.auth.TokenSigner writes them.
  const std::string claims = "{\"c\":" + jsonString(identity.componentId) +
                             ",\"s\":" + jsonString(identity.subarchitecture) +
                             ",\"p\":" + (identity.privileged ? "true" : "false") +
                             ",\"iat\":" + std::to_string(issuedAt) + "}";
  const std::string signingInput = std::string(kHeader) + "." + detail::base64UrlEncode(claims);
  return signingInput + "." + detail::signHs256(signingInput, secret);
}

}  // namespace cast
