package cast.client;

import java.util.ArrayList;
import java.util.List;
import org.junit.jupiter.api.AfterEach;

/**
 * The base of tests whose components share one in-memory fake system (SAs vision and motor):
 * {@link #connect} binds a component to it, and every component connected is closed after
 * the test, so a failing assertion leaves no dispatcher thread behind.
 */
abstract class WithFakeMemory {
  final FakeTransport.Memory memory = new FakeTransport.Memory("vision", "motor");
  final List<Component> components = new ArrayList<>();

  @AfterEach
  void closeComponents() {
    for (Component c : components) {
      c.close();
    }
  }

  /** {@code c} bound to the fake system as component {@code id} of {@code sa}. */
  <C extends Component> C connect(C c, String id, String sa) {
    components.add(FakeTransport.connect(c, memory, id, sa));
    return c;
  }
}
