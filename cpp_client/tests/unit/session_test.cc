// Who a component is after bind(): the identity the server verified from the
// token at Register (RegisterResponse), compared with the one it was started
// as, against the in-memory transport.
#include <gtest/gtest.h>

#include "cast/component.h"
#include "cast_testing.pb.h"
#include "component_core.h"  // IdentityMismatchError, which makes the runner exit 2
#include "fake_transport.h"

namespace {

using cast::Identity;
using cast::testing::FakeTransport;

std::shared_ptr<FakeTransport> transport(const Identity& started, std::optional<Identity> verified) {
  auto t = std::make_shared<FakeTransport>(started);
  t->verified = std::move(verified);
  return t;
}

TEST(Session, PrivilegeIsWhatTheServerVerified) {
  cast::UnmanagedComponent raised;
  raised.bind(transport({"planner", "vision", false}, Identity{"planner", "vision", true}));
  EXPECT_TRUE(raised.privileged());

  cast::UnmanagedComponent lowered;
  lowered.bind(transport({"planner", "vision", true}, Identity{"planner", "vision", false}));
  EXPECT_FALSE(lowered.privileged()) << "the server's word wins over what the component was given";
}

TEST(Session, AServerThatDoesNotSayLeavesTheGivenIdentity) {
  cast::UnmanagedComponent c;
  c.bind(transport({"planner", "vision", true}, std::nullopt));
  EXPECT_EQ(c.componentId(), "planner");
  EXPECT_TRUE(c.privileged());
}

TEST(Session, ATokenOfAnotherComponentFailsTheStartNamingBoth) {
  auto t = transport({"writer", "vision", false}, Identity{"reader", "vision", false});
  cast::UnmanagedComponent c;
  try {
    c.bind(t);
    FAIL() << "no error";
  } catch (const cast::detail::IdentityMismatchError& e) {
    const std::string& m = e.message();
    EXPECT_EQ(std::string(e.name()), "InvalidArgumentError");
    EXPECT_NE(m.find("started as 'writer' in subarchitecture 'vision' (CAST_COMPONENT_ID, CAST_SUBARCHITECTURE)"),
              std::string::npos)
        << m;
    EXPECT_NE(m.find("verified its token as 'reader' in subarchitecture 'vision'"), std::string::npos) << m;
    EXPECT_NE(m.find("`cast token writer --sa vision`"), std::string::npos) << m;
  }
  // The connection is closed at once, and nothing acts under the wrong identity.
  EXPECT_TRUE(t->closed);
  cast::testing::Counter value;
  EXPECT_THROW(c.add("x", value), cast::CastError);
  EXPECT_EQ(t->calls["add"], 0);
}

TEST(Session, ATokenForAnotherSubarchitectureFailsTheStartToo) {
  cast::ManagedComponent c;
  try {
    c.bind(transport({"writer", "vision", false}, Identity{"writer", "language", false}));
    FAIL() << "no error";
  } catch (const cast::InvalidArgumentError& e) {
    EXPECT_NE(e.message().find("'writer' in subarchitecture 'vision'"), std::string::npos) << e.message();
    EXPECT_NE(e.message().find("'writer' in subarchitecture 'language'"), std::string::npos) << e.message();
  }
  EXPECT_THROW(c.proposeTask("t"), cast::CastError) << "a closed component proposes nothing";
}

TEST(Session, TheMismatchKeepsItsTypeWhenRaisedAgain) {
  // Errors kept as shared_ptr<CastError> are rethrown with raise(): the
  // runner must still tell this one from a failed start.
  std::shared_ptr<cast::CastError> kept = std::make_shared<cast::detail::IdentityMismatchError>("m");
  EXPECT_THROW(kept->raise(), cast::detail::IdentityMismatchError);
}

}  // namespace
