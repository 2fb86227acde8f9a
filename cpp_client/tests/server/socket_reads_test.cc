// Gets on the shared-memory session's socket (src/grpc_transport.cc, get;
// WriteStream::read) against the repository's Python server: a C++ component
// on the server's host sends its get as a WriteRequest in a WRITES frame,
// after its writes (docs/client-protocol.md, "Writes on the session's
// socket", "Reads on the socket"). Each get is one more request on the
// session's socket (SessionWrites::sent) and reads what the unary Get would:
// the last of the writes pipelined before it, a large value lent (and given
// back), NotFoundError for a missing entry. A renewed token gives the gets
// after it a new session. A session whose server did not say it answers gets
// there (SharedMemoryInfo.reads false: an earlier release) gets unary calls.
#include <google/protobuf/wrappers.pb.h>
#include <gtest/gtest.h>

#include <future>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include "cast/cast.h"
#include "cast_server.h"
#include "shm_session.h"
#include "transport.h"

namespace {

using namespace std::chrono_literals;
using cast::detail::ClientSession;
using cast::testing::CastServer;
using cast::testing::eventually;
using cast::testing::image;
using cast::testing::kMiB;
using cast::testing::sharedServer;
using google::protobuf::BytesValue;

// A component of `sa` "vision" and its transport, whose shared-memory session
// the test looks at (Transport::sharedSession).
struct SocketReader {
  SocketReader(const CastServer& server, const std::string& id, cast::TransportOptions options = {})
      : transport(cast::connectGrpc(server.endpoint(), server.token(id, "vision"), cast::Identity{id, "vision", false},
                                    options)),
        component(cast::connect(transport)) {}
  std::shared_ptr<ClientSession> session() const { return transport->sharedSession("vision"); }

  std::shared_ptr<cast::detail::Transport> transport;
  std::unique_ptr<cast::Connection> component;
};

TEST(SocketReads, AGetGoesOnTheSessionsSocketAndSeesTheWritesPipelinedBeforeIt) {
  SocketReader reader(sharedServer(), "sr-reader");
  auto& c = *reader.component;
  c.add("sr-n", image(8, 0));
  const std::shared_ptr<ClientSession> session = reader.session();
  ASSERT_TRUE(session);
  ASSERT_TRUE(session->reads());  // this server answers gets on the socket, and says so
  std::uint64_t sent = session->writes().sent();
  EXPECT_TRUE(c.get<BytesValue>("sr-n").value() == image(8, 0).value());
  EXPECT_EQ(session->writes().sent(), sent + 1);  // the get was one more request on the socket
  std::vector<std::future<cast::WriteResult>> pipelined;
  for (int i = 1; i <= 50; ++i) pipelined.push_back(c.overwriteAsync("sr-n", image(16 + i, i)));
  // Sent after the 50 writes on the same socket, answered in order with them: it sees them all.
  const cast::Entry<BytesValue> entry = c.getEntry<BytesValue>("sr-n");
  EXPECT_TRUE(entry.value.value() == image(66, 50).value());
  std::vector<std::uint64_t> versions;
  for (auto& f : pipelined) versions.push_back(f.get().version);
  EXPECT_EQ(entry.version, versions.back());
  EXPECT_EQ(reader.session(), session);
  EXPECT_EQ(session->writes().sent(), sent + 1 + 50 + 1);
}

TEST(SocketReads, ALargeValueReadOnTheSocketIsLentAndGivenBackAndAMissingEntryIsNotFound) {
  CastServer& server = sharedServer();
  auto writer = server.connect("sr-big-writer", "vision");
  SocketReader reader(server, "sr-big-reader");
  const BytesValue big = image(kMiB, 3);
  writer->add("sr-img", big);
  const std::shared_ptr<ClientSession> session = reader.session();
  ASSERT_TRUE(session);
  const auto before = cast::testing::sharedMemoryFigures(server);
  std::uint64_t sent = session->writes().sent();
  {
    cast::ValueView view = reader.component->getView("sr-img");
    EXPECT_EQ(session->writes().sent(), ++sent);
    EXPECT_TRUE(view.shared());  // lent on the read call the get named, its segment before the reply
    EXPECT_EQ(view.author(), "sr-big-writer");
    EXPECT_TRUE(view.field(1).chars() == big.value());
    EXPECT_TRUE(reader.component->get<BytesValue>("sr-img").value() == big.value());
    EXPECT_EQ(session->writes().sent(), ++sent);
  }
  EXPECT_GE(cast::testing::sharedMemoryFigures(server).lent() - before.lent(), 2u);
  try {
    reader.component->get<BytesValue>("sr-missing");
    ADD_FAILURE() << "a get of a missing entry returned";
  } catch (const cast::NotFoundError& e) {
    EXPECT_NE(std::string(e.what()).find("sr-missing"), std::string::npos) << e.what();
  }
  EXPECT_EQ(session->writes().sent(), ++sent);  // refused on the socket too, as the unary call would be
  // What was lent on those calls is given back once nothing holds it.
  EXPECT_TRUE(eventually([&] { return cast::testing::sharedMemoryFigures(server).lent_bytes() == 0; }))
      << cast::testing::sharedMemoryFigures(server).lent_bytes();
}

TEST(SocketReads, AGetAfterTheTokenWasRenewedGoesOnTheNewSession) {
  CastServer& server = sharedServer();
  const std::string path = server.dir() + "/sr-renewed.token";
  cast::testing::writeTokenFile(path, server.token("sr-renewed", "vision"));
  cast::TransportOptions options;
  options.tokenFile = path;
  SocketReader reader(server, "sr-renewed", options);
  reader.component->add("sr-t", image(8, 1));
  EXPECT_TRUE(reader.component->get<BytesValue>("sr-t").value() == image(8, 1).value());
  const std::shared_ptr<ClientSession> first = reader.session();
  ASSERT_TRUE(first);
  std::this_thread::sleep_for(1100ms);  // a token issued later differs; the file is looked at once a second
  cast::testing::writeTokenFile(path, server.token("sr-renewed", "vision"));
  // A get on the socket carries the session's identity: a session opened with the new token takes it.
  EXPECT_TRUE(reader.component->get<BytesValue>("sr-t").value() == image(8, 1).value());
  const std::shared_ptr<ClientSession> second = reader.session();
  ASSERT_TRUE(second);
  EXPECT_NE(second, first);
  EXPECT_TRUE(first->dead());
  EXPECT_EQ(second->writes().sent(), 1u);  // the get
}

TEST(SocketReads, ASessionWhoseServerDoesNotAnswerGetsThereGetsTheUnaryCall) {
  CastServer& server = sharedServer();
  auto writer = server.connect("sr-old-writer", "vision");
  SocketReader reader(server, "sr-old-reader");
  const BytesValue big = image(kMiB, 4);
  writer->add("sr-old", big);
  writer->add("sr-old-small", image(8, 5));
  const std::shared_ptr<ClientSession> session = reader.session();
  ASSERT_TRUE(session);
  session->setReads(false);  // as from a server of an earlier release: SharedMemoryInfo.reads unset
  const std::uint64_t sent = session->writes().sent();
  EXPECT_TRUE(reader.component->get<BytesValue>("sr-old-small").value() == image(8, 5).value());
  {
    cast::ValueView view = reader.component->getView("sr-old");
    EXPECT_TRUE(view.shared());  // lent all the same, on the unary call
    EXPECT_TRUE(view.field(1).chars() == big.value());
  }
  EXPECT_THROW(reader.component->get<BytesValue>("sr-old-missing"), cast::NotFoundError);
  EXPECT_EQ(session->writes().sent(), sent);  // none of them went on the socket
  reader.component->add("sr-old-2", image(8, 6));
  EXPECT_EQ(session->writes().sent(), sent + 1);  // writes still do
}

TEST(SocketReads, AGetWhoseSessionEndsBeforeItsReplyIsMadeAgainAsTheUnaryCall) {
  SocketReader reader(sharedServer(), "sr-ended");
  reader.component->add("sr-e", image(8, 7));
  const std::shared_ptr<ClientSession> session = reader.session();
  ASSERT_TRUE(session);
  ASSERT_TRUE(session->reads());
  // A frame of a kind the server does not know, ahead of the get on the same socket: the server ends the
  // session without reading the get, which this thread's own read of the socket then finds outstanding.
  const std::string unknown{'\x02', '\x00', '\x00', '\x00', '\x63', '?'};
  session->send(unknown);
  EXPECT_TRUE(reader.component->get<BytesValue>("sr-e").value() == image(8, 7).value());
  EXPECT_TRUE(session->dead());
}

}  // namespace
