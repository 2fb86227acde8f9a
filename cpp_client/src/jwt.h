// The pieces of a JSON Web Token (RFC 7519) that credentials.cc mints and
// reads tokens with; the testing kit makes its secrets with base64UrlEncode.
// Internal, not installed.
#pragma once

#include <optional>
#include <string>

namespace cast::detail {

// base64url without padding (RFC 7515, section 2), as JWTs write their parts.
std::string base64UrlEncode(const std::string& bytes);
// The bytes of base64url text (padding optional); nullopt if it is not base64url.
std::optional<std::string> base64UrlDecode(const std::string& text);
// The JWT signature of `signingInput` ("header.payload"): base64url(HMAC-SHA256(secret, input)).
std::string signHs256(const std::string& signingInput, const std::string& secret);

}  // namespace cast::detail
