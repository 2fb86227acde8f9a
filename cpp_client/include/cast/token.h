// Component tokens (docs/client-protocol.md, "Identity and metadata"): JSON Web
// Tokens signed with HS256 and the system's secret,
//
//   base64url({"alg":"HS256","typ":"JWT"}) . base64url(claims) . base64url(HMAC-SHA256)
//
// with the claims {"c": component id, "s": SA, "p": privileged, "iat": issued}
// and "exp" when the token expires. The server verifies every token; a client
// only reads the claims to learn its own identity, and mints one itself only
// when it holds the system's secret (cast::connect from a script).
#pragma once

#include <cstdint>
#include <optional>
#include <string>

#include "cast/transport.h"

namespace cast {

// What a token says about its holder, read without verifying it; nullopt if
// it is not a CAST token (a JWT whose claims carry "c", "s" and "p").
std::optional<Identity> peekToken(const std::string& token);

// A token for `identity` signed with `secret`, issued at `issuedAt` (seconds
// since the epoch), with no expiry: what `cast token` would issue. The server
// accepts it if `secret` is the system's secret. InvalidArgumentError for a
// secret shorter than 32 bytes, which HS256 does not allow (RFC 7518, 3.2).
std::string mintToken(const std::string& secret, const Identity& identity, std::int64_t issuedAt);

namespace detail {
// base64url without padding (RFC 7515, section 2), as JWTs write their parts.
std::string base64UrlEncode(const std::string& bytes);
// The bytes of base64url text (padding optional); nullopt if it is not base64url.
std::optional<std::string> base64UrlDecode(const std::string& text);
// The JWT signature of `signingInput` ("header.payload"): base64url(HMAC-SHA256(secret, input)).
std::string signHs256(const std::string& signingInput, const std::string& secret);
}  // namespace detail

}  // namespace cast
