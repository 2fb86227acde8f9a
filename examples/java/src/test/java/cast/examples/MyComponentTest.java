package cast.examples;

import static org.junit.jupiter.api.Assertions.assertEquals;

import cast.client.Args;
import cast.testing.Actor;
import cast.testing.CastExtension;
import cast.testing.LocalSystem;
import cast.testing.RunningComponent;
import java.nio.file.Path;
import org.junit.jupiter.api.Test;
import org.junit.jupiter.api.extension.RegisterExtension;

/** MyComponent under test: a real CAST system of the example's configuration for each test (cast-testing). */
class MyComponentTest {
  @RegisterExtension static final CastExtension CAST = CastExtension.withConfig(Path.of("system.yaml"));

  @Test
  void answersAGreetingThroughItsTaskManager(LocalSystem system) {
    RunningComponent<MyComponent> answerer =
        system.run(new MyComponent(), "answerer", "greetings", Args.fromJson("{\"prefix\": \"hi, \"}"));
    Actor greeter = system.actAs("greeter", "greetings");
    greeter.add("g1", Greeting.newBuilder().setText("world").setFrom("greeter").build());

    Greeting reply = system.waitForEntry("greetings", "reply-g1", Greeting.class,
        Greeting.newBuilder().setText("hi, world").setFrom("answerer").setReplyTo("g1").build()).value();
    assertEquals("hi, world", reply.getText());
    assertEquals(0, answerer.stop());
  }
}
