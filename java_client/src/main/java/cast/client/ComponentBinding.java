package cast.client;

import java.security.SecureRandom;
import java.time.Duration;
import java.util.ArrayList;
import java.util.HexFormat;
import java.util.List;
import java.util.concurrent.atomic.AtomicLong;
import java.util.function.Consumer;
import java.util.function.Supplier;
import java.util.logging.Logger;

/**
 * A {@link Component}'s binding to a transport: the session the transport started,
 * the identity the server verified, the dispatcher that runs the component's
 * callbacks and hooks, and the entry ids the component hands out. Part of the
 * {@code component} role of the client file map (docs/design.md, "Client
 * libraries"): Component.java holds the working-memory vocabulary and the
 * lifecycle, this file the binding to a transport. One binding per connection; a
 * component that failed to bind has none.
 */
final class ComponentBinding {
  private static final SecureRandom RANDOM = new SecureRandom();

  final Transport transport;
  final Identity identity; // as the server verified it from the token
  final Dispatcher dispatcher;
  private final String idPrefix;
  private final AtomicLong idCounter = new AtomicLong();

  /**
   * Start the session, learn from the server who {@code owner} is, and let
   * {@code verify} refuse that identity. On failure the transport is closed (which
   * ends the session the server opened for the token's holder) and the failure
   * thrown.
   */
  ComponentBinding(Component owner, Transport transport, Supplier<ComponentState> state, Consumer<Identity> verify) {
    Identity who;
    try {
      who = transport.startSession("java", owner.kind(), state);
      verify.accept(who);
    } catch (RuntimeException e) {
      transport.close(); // ends the session the server opened for the token's holder
      throw e;
    }
    this.identity = who;
    this.dispatcher =
        new Dispatcher(
            who.componentId(), owner.maxPendingCallbacks(), Logger.getLogger("cast.component." + who.componentId()));
    byte[] salt = new byte[3];
    RANDOM.nextBytes(salt);
    // Unique across components (the id) and across restarts of one component (the salt).
    this.idPrefix = who.componentId() + ":" + HexFormat.of().formatHex(salt) + ":";
    // Change delivery stopped: for one watch (watchId >= 0, which is dropped) or for all.
    transport.setEventSink(
        new Transport.EventSink() {
          @Override
          public void event(Transport.Change change) {
            dispatcher.deliver(change);
          }

          @Override
          public void event(Transport.Change change, java.util.function.BooleanSupplier overflow) {
            dispatcher.deliver(change, overflow);
          }

          @Override
          public void readBy(SessionSocket socket) {
            if (socket.nudges()) { // else the dispatcher, blocked in its read, could not be woken
              dispatcher.attach(socket);
            }
          }
        },
        (error, watchId) -> {
          dispatcher.stopped(error, watchId);
          dispatcher.submitHook(() -> owner.watchFailed(error));
        });
    this.transport = transport;
  }

  /** A fresh entry id, unique across components and restarts. */
  String newId() {
    return idPrefix + idCounter.incrementAndGet();
  }

  /**
   * Watch {@code filters} (checked for null here; "local" ones resolved to the own SA,
   * which only the binding knows) with {@code callback} on the dispatcher thread, as
   * {@code options} say.
   */
  WatchHandle watch(List<ChangeFilter> filters, ChangeCallback callback, WatchOptions options) {
    List<ChangeFilter> resolved = new ArrayList<>();
    for (ChangeFilter f : filters) {
      if (f == null) {
        throw new InvalidArgumentError("onChange filters must not be null");
      }
      resolved.add(f.isLocal() ? f.inSubarchitecture(identity.subarchitecture()) : f);
    }
    return dispatcher.watch(transport, resolved, callback, options);
  }

  /** Queued callbacks run, then the session ends (locks and tasks released). */
  void close() {
    dispatcher.stop(Duration.ofSeconds(5));
    transport.close();
  }
}
