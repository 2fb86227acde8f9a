#include "cast/token.h"

#include <google/protobuf/struct.pb.h>
#include <google/protobuf/util/json_util.h>
#include <openssl/evp.h>
#include <openssl/hmac.h>

#include <cstdio>

#include "cast/errors.h"

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
