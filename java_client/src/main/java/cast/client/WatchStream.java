package cast.client;

import cast.v1.ChangeEvent;
import cast.v1.WatchCancel;
import cast.v1.WatchCreate;
import cast.v1.WatchRequest;
import cast.v1.WatchResponse;
import com.google.protobuf.InvalidProtocolBufferException;
import io.grpc.Metadata;
import io.grpc.Status;
import io.grpc.stub.ClientCallStreamObserver;
import io.grpc.stub.ClientResponseObserver;
import java.nio.ByteBuffer;
import java.util.ArrayList;
import java.util.HashMap;
import java.util.LinkedHashMap;
import java.util.List;
import java.util.Map;
import java.util.concurrent.CompletableFuture;
import java.util.concurrent.ConcurrentHashMap;
import java.util.concurrent.ExecutionException;
import java.util.concurrent.TimeUnit;
import java.util.concurrent.TimeoutException;
import java.util.concurrent.atomic.AtomicInteger;
import java.util.function.BiConsumer;
import java.util.function.BooleanSupplier;
import java.util.logging.Logger;

/**
 * The Watch stream to one server, shared by every watch of the component on that
 * server (docs/client-protocol.md, "Watching" and "Reconnection"). When the
 * connection breaks it is opened again with backoff and every watch is created
 * again from the revision after the last one it got, per SA, with the server's
 * history id: a server that lost that history refuses the resume, and the component
 * is told to resynchronise (HistoryExpiredError). Any other end is for good: every
 * watch on the stream fails, and the next {@code onChange} opens a new stream
 * ({@link Streams}: the component's streams, one per server).
 *
 * <p>With a shared-memory session the call asks for its event batches as EVENTS frames on the
 * session's socket (docs/client-protocol.md, "A watch's events on the session's socket"): the
 * session's reader thread turns them into changes and queues them on the dispatcher itself, so an
 * event crosses no gRPC thread; {@code created}, {@code failed} and the call's end stay on the
 * call. When the socket ends the call is ended and opened again as after any break, from the
 * revision after the last event delivered. The twin of python/cast/client/watch_stream.py and
 * cpp_client/src/watch_stream.cc.
 */
final class WatchStream {
  private static final Logger LOG = Logger.getLogger("cast.client");

  /** What the client keeps of one watch so that it can be created again after a reconnect. */
  static final class Watch {
    final int watchId;
    final List<cast.v1.ChangeFilter> filters;
    final Map<String, Long> firstStarts;
    final cast.v1.Delivery delivery;
    private List<String> sas = List.of(); // the SAs of this server the watch covers (known once created)
    private Map<String, Long> base; // per SA, the revision the watch has seen up to (null until created)

    Watch(int watchId, List<cast.v1.ChangeFilter> filters, Map<String, Long> firstStarts, cast.v1.Delivery delivery) {
      this.watchId = watchId;
      this.filters = List.copyOf(filters);
      this.firstStarts = Map.copyOf(firstStarts);
      this.delivery = delivery;
    }

    /** Whether the server confirmed the watch (a later create of it is a resume). */
    boolean isCreated() {
      return base != null;
    }

    /**
     * The server confirmed the watch at {@code revisions} (every SA of the server): the
     * watch has seen up to the revision before its start, per SA it covers.
     */
    void created(Map<String, Long> revisions) {
      if (base != null) {
        return; // a resume's confirmation: the watch already knows where it is
      }
      boolean coversAll = filters.stream().anyMatch(f -> f.getSubarchitecture().isEmpty());
      List<String> covered = new ArrayList<>();
      Map<String, Long> upTo = new HashMap<>();
      for (var r : revisions.entrySet()) {
        String sa = r.getKey();
        if (coversAll || filters.stream().anyMatch(f -> f.getSubarchitecture().equals(sa))) {
          covered.add(sa);
          upTo.put(sa, firstStarts.getOrDefault(sa, r.getValue() + 1) - 1);
        }
      }
      sas = covered;
      base = upTo;
    }

    /**
     * Where a create of this watch starts, per SA: its first start revisions until the
     * server confirmed it; after that (a resume) the revision after the newest one the
     * watch or its stream ({@code seen}) got, and the watch moves up to there, so a
     * later resume never goes back before it.
     */
    Map<String, Long> starts(Map<String, Long> seen) {
      if (base == null) {
        return firstStarts;
      }
      Map<String, Long> starts = new HashMap<>();
      Map<String, Long> upTo = new HashMap<>();
      for (String sa : sas) {
        long revision = Math.max(base.getOrDefault(sa, 0L), seen.getOrDefault(sa, 0L));
        starts.put(sa, revision + 1);
        upTo.put(sa, revision);
      }
      base = upTo;
      return starts;
    }
  }

  /**
   * The component's Watch streams, one per server, and which watch is on which: a watch
   * goes to every server whose SAs its filters can match, all or nothing. A stream that
   * ended for good is replaced by the next watch, so {@code watchFailed} can register
   * the component's callbacks again.
   */
  static final class Streams {
    private final GrpcTransport transport;
    private final Object lock = new Object();
    private final Map<GrpcServer, WatchStream> streams = new HashMap<>(); // guarded by lock
    private boolean closed; // guarded by lock
    private final Map<Integer, List<GrpcServer>> placed = new ConcurrentHashMap<>();
    private volatile Transport.EventSink sink;
    private volatile BiConsumer<CastError, Integer> onError =
        (err, watchId) -> LOG.severe("change delivery stopped: " + err.getMessage());

    Streams(GrpcTransport transport) {
      this.transport = transport;
    }

    void setSink(Transport.EventSink sink, BiConsumer<CastError, Integer> onError) {
      this.sink = sink;
      this.onError = onError;
    }

    BiConsumer<CastError, Integer> errors() {
      return onError;
    }

    /** Create the watch on every server its filters can match; the revisions at creation, per SA. */
    Map<String, Long> create(
        int watchId, List<ChangeFilter> filters, Map<String, Long> startRevisions, Delivery delivery) {
      if (sink == null) {
        throw new IllegalStateException("setEventSink must be called before watch");
      }
      List<cast.v1.ChangeFilter> wire = new ArrayList<>();
      List<GrpcServer> targets = new ArrayList<>();
      for (ChangeFilter f : filters) {
        wire.add(Conversions.filter(f));
        for (GrpcServer s :
            f.subarchitecture().isEmpty() ? transport.allServers() : List.of(transport.server(f.subarchitecture()))) {
          if (!targets.contains(s)) {
            targets.add(s);
          }
        }
      }
      Map<String, Long> revisions = new HashMap<>();
      List<WatchStream> created = new ArrayList<>();
      try {
        for (GrpcServer server : targets) {
          WatchStream stream;
          synchronized (lock) {
            if (closed || transport.isClosing()) {
              throw new UnavailableError("the component's connection is closed");
            }
            // A stream that ended (server restart, history expired) is replaced.
            stream = streams.get(server);
            if (stream == null || stream.isEnded()) {
              stream = new WatchStream(transport, server, this);
              streams.put(server, stream);
            }
          }
          Map<String, Long> mine = new HashMap<>();
          startRevisions.forEach((sa, rev) -> {
            if (transport.server(sa) == server) {
              mine.put(sa, rev);
            }
          });
          revisions.putAll(stream.create(watchId, wire, mine, Conversions.delivery(delivery)));
          created.add(stream);
        }
      } catch (RuntimeException e) {
        // All or nothing: do not leave half a watch behind on the servers that accepted it.
        for (WatchStream s : created) {
          s.cancel(watchId);
        }
        throw e;
      }
      placed.put(watchId, targets);
      return revisions;
    }

    /** Remove the watch from every server it is on. */
    void cancel(int watchId) {
      List<GrpcServer> targets = placed.remove(watchId);
      if (targets == null) {
        return;
      }
      for (GrpcServer server : targets) {
        WatchStream stream;
        synchronized (lock) {
          stream = streams.get(server);
        }
        if (stream != null) {
          stream.cancel(watchId);
        }
      }
    }

    /** How many times the streams were opened again after a break (for tests and diagnostics). */
    int reconnects() {
      synchronized (lock) {
        return streams.values().stream().mapToInt(s -> s.reconnects.get()).sum();
      }
    }

    /** End every stream (the component is closing); no new one opens. */
    void close() {
      List<WatchStream> all;
      synchronized (lock) {
        closed = true;
        all = new ArrayList<>(streams.values());
      }
      for (WatchStream s : all) {
        s.close();
      }
    }
  }

  private final GrpcTransport transport;
  private final GrpcServer server;
  private final Streams streams;
  private final Object mutex = new Object();
  private final Map<Integer, Watch> watches = new LinkedHashMap<>(); // guarded by mutex
  private final Map<Integer, CompletableFuture<Map<String, Long>>> pending = new ConcurrentHashMap<>();
  // The newest revision per SA received on this stream: the server moves every watch of an SA
  // on one stream past the events it sends, so each watch has seen at least this far.
  private final Map<String, Long> seen = new ConcurrentHashMap<>();
  private final Backoff backoff = new Backoff();
  private ClientCallStreamObserver<WatchRequest> requests; // the current call; guarded by mutex
  private int generation; // numbers the calls; guarded by mutex
  private int upgrading; // the call ended to be opened again with shared memory; guarded by mutex
  private volatile String historyId = "";
  private volatile boolean connected;
  private volatile boolean dead; // ended for good: a new watch needs a new stream
  private volatile boolean closed;
  final AtomicInteger reconnects = new AtomicInteger();

  /** Opens the stream to {@code server}; events and failures go where {@code streams} says. */
  WatchStream(GrpcTransport transport, GrpcServer server, Streams streams) {
    this.transport = transport;
    this.server = server;
    this.streams = streams;
    open();
  }

  /** Whether the stream ended for good (a new watch needs a new stream). */
  boolean isEnded() {
    return dead;
  }

  private WatchRequest createRequest(Watch w) {
    // The history id guards a resume only: a first create starts wherever the server is.
    String history = w.isCreated() ? historyId : "";
    Map<String, Long> starts = w.starts(seen);
    return WatchRequest.newBuilder()
        .setCreate(
            WatchCreate.newBuilder()
                .setWatchId(w.watchId)
                .addAllFilters(w.filters)
                .putAllStartRevisions(starts)
                .setDelivery(w.delivery)
                .setHistoryId(history))
        .build();
  }

  /** Send on the current call (under mutex); a call that just ended drops it, the reopen resends. */
  private void send(WatchRequest req) {
    if (requests == null) {
      return;
    }
    try {
      requests.onNext(req);
    } catch (IllegalStateException e) {
      LOG.fine("watch request not sent, the call ended: " + e.getMessage());
    }
  }

  private void open() {
    // The call's part of the shared-memory session with the server (large values lent, not
    // sent), asked for outside the mutex: opening a session may take a round trip.
    SharedLink shared = server.shared;
    SharedSession.ReadCall read = shared == null || closed ? null : shared.newCall();
    synchronized (mutex) {
      if (closed || transport.isClosing()) {
        if (read != null) {
          read.end(false);
        }
        return;
      }
      int gen = ++generation;
      requests = null;
      Call call = new Call(gen, read);
      if (read != null) {
        read.session().onEvents(read.number, call); // before the call starts: a frame may precede `created`
        Transport.EventSink sink = streams.sink;
        if (sink != null) {
          sink.readBy(read.session().io()); // the component's dispatcher reads the events itself, where it can
        }
      }
      SharedLink.watching(server.wmAsync, read).watch(call); // beforeStart sets `requests`
      for (Watch w : watches.values()) {
        send(createRequest(w));
      }
    }
  }

  /**
   * The observer of one Watch call, and of its EVENTS frames on the session's socket. Its events
   * (from either) are delivered under {@code delivering}, which the call's end takes before the
   * call is opened again: no event of an ended call is delivered after the resume was computed.
   */
  private final class Call
      implements ClientResponseObserver<WatchRequest, WatchResponse>, SharedSession.EventsHandler {
    private final int gen;
    private final SharedSession.ReadCall read; // its part of the shared-memory session, or null
    private final BooleanSupplier overflow; // the session's reader must not wait for room meanwhile
    private final Object delivering = new Object();
    private boolean over; // the call ended: its frames still coming are dropped; guarded by delivering
    private volatile boolean unreadable; // an event's lent value could not be read: the call is being ended
    private boolean first = true; // onNext is serial per call

    Call(int gen, SharedSession.ReadCall read) {
      this.gen = gen;
      this.read = read;
      SharedSession session = read == null ? null : read.session();
      this.overflow = session == null ? () -> false : session::mustRead;
    }

    @Override
    public void frame(ByteBuffer body) {
      WatchResponse resp;
      try {
        resp = WatchResponse.parseFrom(body);
      } catch (InvalidProtocolBufferException e) {
        // Nothing of it can be delivered: the call resumes after the last event that was.
        LOG.warning("an EVENTS frame from " + server.endpoint + " is not a WatchResponse (" + e.getMessage()
            + "): reconnecting");
        unreadable = true;
        cancel(gen, "an EVENTS frame could not be read");
        return;
      }
      deliver(resp);
    }

    @Override
    public void sessionEnded(String why) {
      // The server ends the call too (UNAVAILABLE); ending it here does not wait for that. It is
      // opened again as after any break (with backoff, so a session that keeps ending cannot spin).
      cancel(gen, "its shared-memory session ended (" + why + ")");
    }

    /** The events of {@code resp}, unless the call is over; an unreadable lent value ends the call. */
    private void deliver(WatchResponse resp) {
      if (resp.getEventsCount() == 0) {
        return;
      }
      synchronized (delivering) {
        if (over || unreadable) {
          return; // sent again after the reconnect
        }
        try {
          events(resp, read, overflow);
        } catch (UnavailableError e) {
          // A value lent by shared memory that cannot be read (its segment never came): the
          // stream is opened again and resumes from the last event delivered, so nothing is lost.
          unreadable = true;
          LOG.warning("an event from " + server.endpoint + " could not be read (" + e.getMessage() + "): reconnecting");
          cancel(gen, "an event could not be read: " + e.getMessage());
        }
      }
    }

    /** No event of the call is delivered from now on (its end, before the resume is computed). */
    private void over() {
      synchronized (delivering) {
        over = true;
      }
      if (read != null) {
        read.session().offEvents(read.number);
      }
    }

    @Override
    public void beforeStart(ClientCallStreamObserver<WatchRequest> requestStream) {
      synchronized (mutex) {
        if (gen == generation) {
          requests = requestStream;
        }
      }
    }

    @Override
    public void onNext(WatchResponse resp) {
      // grpc-java calls this serially per call, so events keep the server's order.
      if (unreadable) {
        return; // sent again after the reconnect
      }
      if (!connected) {
        connected = true;
        backoff.reset();
      }
      if (first) {
        first = false;
        // Without a session (or with one that ended before the call began) it opens again once one is open.
        if ((read == null || read.session().dead() != null) && server.shared != null) {
          transport.schedule(() -> upgrade(gen), 0);
        }
      }
      deliver(resp); // events come on the call without a session (or from a server that has none)
      if (!unreadable) {
        handle(resp);
      }
    }

    @Override
    public void onError(Throwable t) {
      over();
      endRead();
      ended(gen, Status.fromThrowable(t), Status.trailersFromThrowable(t));
    }

    @Override
    public void onCompleted() {
      over();
      endRead();
      ended(
          gen,
          Status.UNAVAILABLE.withDescription("the server at " + server.endpoint + " ended the watch stream"),
          null);
    }

    /** The call is over: the server takes back what it lent on it and this client never received. */
    private void endRead() {
      if (read != null) {
        read.end(false);
      }
    }
  }

  /**
   * A stream opened without a shared-memory session (its server was away, or had none) is
   * opened again once one is open: it resumes where it is, and large values come lent.
   */
  private void upgrade(int gen) {
    SharedLink shared = server.shared;
    if (shared == null || shared.session() == null) {
      return;
    }
    reopen(gen, "opened again with shared memory");
  }

  /** End call {@code gen}, if it is still the current one, and open it again at once (nothing broke on gRPC). */
  private void reopen(int gen, String why) {
    synchronized (mutex) {
      if (gen != generation || requests == null) {
        return;
      }
      upgrading = gen;
    }
    cancel(gen, why);
  }

  /** End call {@code gen}, if it is still the current one (it is opened again). */
  private void cancel(int gen, String why) {
    synchronized (mutex) {
      if (gen == generation && requests != null) {
        try {
          requests.cancel(why, null);
        } catch (RuntimeException e) {
          LOG.fine("watch call already ended: " + e.getMessage());
        }
      }
    }
  }

  /** Deliver the events of {@code resp} (under its call's {@code delivering}), in order. */
  private void events(WatchResponse resp, SharedSession.ReadCall read, BooleanSupplier overflow) {
    Transport.EventSink sink = streams.sink;
    for (ChangeEvent e : resp.getEventsList()) {
      if (sink != null) {
        Transport.Change change = null;
        try {
          change = Conversions.change(e, read);
        } catch (UnavailableError err) {
          throw err; // not delivered, not seen: the resume sends it again
        } catch (CastError err) {
          // An event this library cannot represent must not break the stream for the others.
          LOG.severe("dropping change event revision " + e.getRevision() + ": " + err.getMessage());
        }
        if (change != null) {
          sink.event(change, overflow);
        }
      }
      seen.merge(e.getAddress().getSubarchitecture(), e.getRevision(), Math::max);
    }
  }

  /** What the call itself carries besides events: the creation or failure of a watch. */
  private void handle(WatchResponse resp) {
    if (resp.hasCreated()) {
      var created = resp.getCreated();
      if (!created.getHistoryId().isEmpty()) {
        historyId = created.getHistoryId();
      }
      synchronized (mutex) {
        Watch w = watches.get(created.getWatchId());
        if (w != null) {
          w.created(created.getRevisionsMap());
        }
      }
      var f = pending.remove(created.getWatchId());
      if (f != null) {
        f.complete(created.getRevisionsMap());
      }
    }
    if (resp.hasFailed()) {
      var failed = resp.getFailed();
      CastError error = Errors.forCode(failed.getCode(), failed.getMessage());
      var f = pending.remove(failed.getWatchId());
      Watch dropped;
      synchronized (mutex) {
        dropped = watches.remove(failed.getWatchId());
      }
      if (f != null) {
        f.completeExceptionally(error);
      } else if (dropped != null) {
        // A resume refused after a reconnect: the history no longer covers it (or the server
        // lost it): the component must resynchronise.
        if (!(error instanceof HistoryExpiredError)) {
          error = new HistoryExpiredError("watch " + failed.getWatchId() + " could not resume: " + failed.getMessage());
        }
        streams.onError.accept(error, failed.getWatchId());
      }
    }
  }

  /** Call {@code gen} ended with {@code status}; {@code trailers} (null for none) may name a precise error. */
  private void ended(int gen, Status status, Metadata trailers) {
    boolean upgraded;
    synchronized (mutex) {
      if (gen != generation) {
        return; // an older call
      }
      requests = null;
      upgraded = upgrading == gen;
    }
    connected = false;
    if (closed || transport.isClosing()) {
      return;
    }
    if (upgraded) {
      transport.schedule(this::open, 0); // at once: nothing broke
      return;
    }
    CastError error = Errors.fromStatus(status, trailers);
    if (!GrpcTransport.TRANSIENT.contains(status.getCode())) {
      fail(error);
      return;
    }
    reconnects.incrementAndGet();
    long delay = backoff.nextMillis();
    LOG.warning(
        "watch stream to " + server.endpoint + " broke (" + status.getCode() + ": " + status.getDescription()
            + "); reconnecting in " + delay + " ms");
    transport.schedule(
        () -> {
          server.channel.resetConnectBackoff(); // try the server now, not after gRPC's own (long) backoff
          open();
        },
        delay);
  }

  /** End the stream for good (fell behind the history, ...): every watch on it fails. */
  private void fail(CastError error) {
    dead = true;
    synchronized (mutex) {
      watches.clear();
    }
    for (Integer id : new ArrayList<>(pending.keySet())) {
      var f = pending.remove(id);
      if (f != null) {
        f.completeExceptionally(error);
      }
    }
    streams.onError.accept(error, -1);
  }

  /** Create a watch and wait for the server to confirm it; returns the revisions at creation. */
  Map<String, Long> create(
      int watchId, List<cast.v1.ChangeFilter> filters, Map<String, Long> starts, cast.v1.Delivery delivery) {
    var done = new CompletableFuture<Map<String, Long>>();
    Watch w = new Watch(watchId, filters, starts, delivery);
    synchronized (mutex) {
      if (dead) {
        throw new UnavailableError("the watch stream to " + server.endpoint + " has ended");
      }
      pending.put(watchId, done);
      watches.put(watchId, w);
      send(createRequest(w)); // while disconnected, the reopen sends it
    }
    long timeout = transport.callTimeout().toMillis();
    try {
      return done.get(timeout, TimeUnit.MILLISECONDS);
    } catch (TimeoutException e) {
      forget(watchId);
      String seconds = timeout / 1000.0 + " s";
      if (!connected) {
        throw new UnavailableError(
            "server " + server.endpoint + " unreachable: the watch was not created within " + seconds);
      }
      synchronized (mutex) {
        if (requests != null) { // the server looks hung: the call opens again and the other watches resume
          requests.cancel("no answer to a watch's creation within " + seconds, null);
        }
      }
      throw new DeadlineExceededError(
          server.endpoint + " did not confirm watch " + watchId + " within " + seconds
              + ": the server looks hung, so the watch stream was ended; it opens again by itself and its other"
              + " watches resume");
    } catch (ExecutionException e) {
      forget(watchId);
      throw Errors.fromThrowable(e.getCause());
    } catch (InterruptedException e) {
      Thread.currentThread().interrupt();
      forget(watchId);
      throw new CastError("CANCELLED", "interrupted while waiting for the server to confirm watch " + watchId);
    }
  }

  private void forget(int watchId) {
    pending.remove(watchId);
    synchronized (mutex) {
      watches.remove(watchId);
    }
  }

  /** Remove a watch on this stream. */
  void cancel(int watchId) {
    synchronized (mutex) {
      watches.remove(watchId);
      send(WatchRequest.newBuilder().setCancel(WatchCancel.newBuilder().setWatchId(watchId)).build());
    }
  }

  /** End the call (the component is closing). */
  void close() {
    closed = true;
    synchronized (mutex) {
      if (requests != null) {
        try {
          requests.cancel("component closing", null);
        } catch (RuntimeException e) {
          LOG.fine("watch call already ended: " + e.getMessage());
        }
        requests = null;
      }
    }
  }
}
