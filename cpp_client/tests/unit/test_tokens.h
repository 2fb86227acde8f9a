// The secret and a token signed with it, shared by the unit tests of
// credentials and of cast::connect (no server signs them).
#pragma once

#include <string>

namespace cast::unit {

// tests/conftest.py's SECRET.
inline const std::string kSecret = "test-secret-0123456789abcdef-0123456789";

// Made with PyJWT: jwt.encode({"c": "planner", "s": "coordination", "p": True,
// "iat": 1700000000, "exp": 1700003600}, kSecret, algorithm="HS256").
inline const std::string kPlannerToken =
    "eyJhbGciOiJIUzI1NiIsInR5cCI6IkpXVCJ9."
    "eyJjIjoicGxhbm5lciIsInMiOiJjb29yZGluYXRpb24iLCJwIjp0cnVlLCJpYXQiOjE3MDAwMDAwMDAsImV4cCI6MTcwMDAwMzYwMH0."
    "mON1cpsY000YjhzfewPiFgGFw69BHVWWsbe6zfS8uGs";

}  // namespace cast::unit
