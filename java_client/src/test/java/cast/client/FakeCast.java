package cast.client;

import cast.v1.*;
import com.google.protobuf.Timestamp;
import io.grpc.Context;
import io.grpc.Contexts;
import io.grpc.ManagedChannel;
import io.grpc.Metadata;
import io.grpc.Server;
import io.grpc.ServerCall;
import io.grpc.ServerCallHandler;
import io.grpc.ServerInterceptor;
import io.grpc.ServerInterceptors;
import io.grpc.Status;
import io.grpc.inprocess.InProcessChannelBuilder;
import io.grpc.inprocess.InProcessServerBuilder;
import io.grpc.stub.ServerCallStreamObserver;
import io.grpc.stub.StreamObserver;
import java.io.IOException;
import java.time.Duration;
import java.util.ArrayList;
import java.util.Collections;
import java.util.HashMap;
import java.util.List;
import java.util.Map;
import java.util.concurrent.CopyOnWriteArrayList;
import java.util.concurrent.atomic.AtomicInteger;

/**
 * An in-process fake of one CAST server, for unit tests that need a server's
 * answers but not its real semantics (those are tested against the real server
 * by tests/interop). Identity: the token is the component id. Writes produce
 * change events; the task manager adopts every proposal.
 */
final class FakeCast implements AutoCloseable {
  static final Context.Key<String> CALLER = Context.key("caller");

  final String name;
  final Map<String, String> saEndpoints; // SA -> endpoint as the directory advertises it
  final Map<String, cast.v1.Entry> entries = Collections.synchronizedMap(new HashMap<>());
  final Map<String, Long> revisions = Collections.synchronizedMap(new HashMap<>());
  final Map<String, String> lockHolders = Collections.synchronizedMap(new HashMap<>());
  final List<RegisterSchemasRequest> schemaRequests = new CopyOnWriteArrayList<>();
  final List<String> calls = new CopyOnWriteArrayList<>(); // "Method sa/id" of every WM call
  final List<RegisterRequest> registrations = new CopyOnWriteArrayList<>();
  final List<HeartbeatRequest> beats = new CopyOnWriteArrayList<>();
  final List<String> endedSessions = new CopyOnWriteArrayList<>();
  final List<WatchStream> watchStreams = new CopyOnWriteArrayList<>();
  final List<StreamObserver<cast.v1.Task>> decisionStreams = new CopyOnWriteArrayList<>();
  final AtomicInteger sessions = new AtomicInteger();
  final List<WatchCreate> creates = new CopyOnWriteArrayList<>();
  final List<StreamObserver<HeartbeatResponse>> heartbeatStreams = new CopyOnWriteArrayList<>();
  volatile String historyId = "history-1";
  final AtomicInteger tasks = new AtomicInteger();
  volatile int leaseMs = 300;
  private final Server server;

  /** A fake named {@code name} (its in-process endpoint) hosting the SAs mapped to it. */
  FakeCast(String name, Map<String, String> saEndpoints) throws IOException {
    this.name = name;
    this.saEndpoints = saEndpoints;
    ServerInterceptor auth =
        new ServerInterceptor() {
          @Override
          public <Q, R> ServerCall.Listener<Q> interceptCall(
              ServerCall<Q, R> call, Metadata headers, ServerCallHandler<Q, R> next) {
            String h = headers.get(Metadata.Key.of("authorization", Metadata.ASCII_STRING_MARSHALLER));
            if (h == null || !h.startsWith("Bearer ")) {
              call.close(Status.UNAUTHENTICATED.withDescription("no token"), new Metadata());
              return new ServerCall.Listener<Q>() {};
            }
            return Contexts.interceptCall(Context.current().withValue(CALLER, h.substring(7)), call, headers, next);
          }
        };
    server =
        InProcessServerBuilder.forName(name)
            .directExecutor()
            .addService(ServerInterceptors.intercept(new Wm(), auth))
            .addService(ServerInterceptors.intercept(new Dir(), auth))
            .addService(ServerInterceptors.intercept(new Tm(), auth))
            .build()
            .start();
  }

  static GrpcTransport.ChannelFactory channels() {
    return endpoint -> InProcessChannelBuilder.forName(endpoint).build();
  }

  /** A component bound to this fake (as the directory) through in-process channels. */
  static <C extends Component> C connect(C component, String directory, String id, String sa) {
    LaunchContract contract = new LaunchContract(directory, id, sa, id, Args.empty());
    component.bind(new GrpcTransport(contract, channels(), Duration.ofSeconds(5)));
    return component;
  }

  @Override
  public void close() {
    server.shutdownNow();
  }

  private static String key(EntryAddress a) {
    return a.getSubarchitecture() + "/" + a.getId();
  }

  private static <T> void fail(StreamObserver<T> obs, Status status, String msg) {
    obs.onError(status.withDescription(msg).asRuntimeException());
  }

  // ------------------------------------------------------------ Directory

  final class Dir extends DirectoryGrpc.DirectoryImplBase {
    @Override
    public void describeSystem(DescribeSystemRequest req, StreamObserver<SystemDescription> obs) {
      var b = SystemDescription.newBuilder().setName("fake").setEndpoint(name);
      saEndpoints.forEach(
          (sa, ep) -> b.addSubarchitectures(SubarchitectureInfo.newBuilder().setName(sa).setEndpoint(ep)));
      obs.onNext(b.build());
      obs.onCompleted();
    }

    @Override
    public void register(RegisterRequest req, StreamObserver<RegisterResponse> obs) {
      registrations.add(req);
      obs.onNext(
          RegisterResponse.newBuilder()
              .setSessionId(name + "-session-" + sessions.incrementAndGet())
              .setLeaseMs(leaseMs)
              .build());
      obs.onCompleted();
    }

    @Override
    public StreamObserver<HeartbeatRequest> heartbeat(StreamObserver<HeartbeatResponse> obs) {
      heartbeatStreams.add(obs);
      return new StreamObserver<>() {
        String session = "";

        @Override
        public void onNext(HeartbeatRequest beat) {
          session = beat.getSessionId();
          beats.add(beat);
          obs.onNext(HeartbeatResponse.newBuilder().setLeaseMs(leaseMs).build());
        }

        @Override
        public void onError(Throwable t) {
          endedSessions.add(session);
        }

        @Override
        public void onCompleted() {
          endedSessions.add(session);
          obs.onCompleted();
        }
      };
    }

    @Override
    public void registerSchemas(RegisterSchemasRequest req, StreamObserver<RegisterSchemasResponse> obs) {
      schemaRequests.add(req);
      obs.onNext(RegisterSchemasResponse.getDefaultInstance());
      obs.onCompleted();
    }
  }

  // --------------------------------------------------------- WorkingMemory

  /** One Watch call: its watches and the observer to send on. */
  final class WatchStream implements StreamObserver<WatchRequest> {
    final ServerCallStreamObserver<WatchResponse> out;
    final Map<Integer, List<cast.v1.ChangeFilter>> watches = Collections.synchronizedMap(new HashMap<>());

    WatchStream(StreamObserver<WatchResponse> out) {
      this.out = (ServerCallStreamObserver<WatchResponse>) out;
    }

    @Override
    public void onNext(WatchRequest req) {
      if (req.hasCreate()) {
        WatchCreate c = req.getCreate();
        creates.add(c);
        if (!c.getHistoryId().isEmpty() && !c.getHistoryId().equals(historyId)) {
          send(
              WatchResponse.newBuilder()
                  .setFailed(
                      WatchFailed.newBuilder()
                          .setWatchId(c.getWatchId())
                          .setCode("OUT_OF_RANGE")
                          .setMessage("history " + c.getHistoryId() + " is gone: resynchronise"))
                  .build());
          return;
        }
        watches.put(c.getWatchId(), c.getFiltersList());
        Map<String, Long> now = new HashMap<>();
        for (String sa : saEndpoints.keySet()) {
          now.put(sa, revisions.getOrDefault(sa, 0L));
        }
        send(
            WatchResponse.newBuilder()
                .setCreated(
                    WatchCreated.newBuilder().setWatchId(c.getWatchId()).putAllRevisions(now).setHistoryId(historyId))
                .build());
      } else if (req.hasCancel()) {
        watches.remove(req.getCancel().getWatchId());
        send(WatchResponse.newBuilder().addCancelled(req.getCancel().getWatchId()).build());
      }
    }

    synchronized void send(WatchResponse r) {
      out.onNext(r);
    }

    @Override
    public void onError(Throwable t) {
      watchStreams.remove(this);
    }

    @Override
    public void onCompleted() {
      watchStreams.remove(this);
      out.onCompleted();
    }
  }

  /** Send one batch of events to every stream, each event tagged with the watches it matches. */
  void publish(List<ChangeEvent> events) {
    for (WatchStream s : watchStreams) {
      var resp = WatchResponse.newBuilder();
      for (ChangeEvent e : events) {
        List<Integer> ids = new ArrayList<>();
        boolean[] withEntry = {false};
        synchronized (s.watches) {
          s.watches.forEach(
              (id, filters) -> {
                for (cast.v1.ChangeFilter f : filters) {
                  if (matches(f, e)) {
                    if (!ids.contains(id)) {
                      ids.add(id);
                    }
                    withEntry[0] |= f.getIncludeEntry();
                  }
                }
              });
        }
        if (!ids.isEmpty()) {
          var ev = e.toBuilder().addAllWatchIds(ids);
          if (!withEntry[0]) {
            ev.clearEntry();
          }
          resp.addEvents(ev);
        }
      }
      if (resp.getEventsCount() > 0) {
        s.send(resp.build());
      }
    }
  }

  /** End every heartbeat stream with {@code status} (the session is gone). */
  void failHeartbeats(Status status) {
    for (var h : heartbeatStreams) {
      heartbeatStreams.remove(h);
      h.onError(status.asRuntimeException());
    }
  }

  /** End every Watch stream with {@code status} (e.g. OUT_OF_RANGE: history expired). */
  void failWatchStreams(Status status) {
    for (WatchStream s : watchStreams) {
      watchStreams.remove(s);
      s.out.onError(status.asRuntimeException());
    }
  }

  static boolean matches(cast.v1.ChangeFilter f, ChangeEvent e) {
    return (f.getOperationsList().isEmpty() || f.getOperationsList().contains(e.getOperation()))
        && (f.getType().isEmpty() || f.getType().equals(e.getType()))
        && (f.getId().isEmpty() || f.getId().equals(e.getAddress().getId()))
        && (f.getSubarchitecture().isEmpty() || f.getSubarchitecture().equals(e.getAddress().getSubarchitecture()))
        && (f.getSourceComponent().isEmpty() || f.getSourceComponent().equals(e.getSourceComponent()));
  }

  /** Apply a write; the event carries the entry after it (for DELETE: as it was), publish strips it unless asked. */
  private ChangeEvent write(cast.v1.Operation op, EntryAddress addr, com.google.protobuf.Any value, long version) {
    String who = CALLER.get();
    long rev = revisions.merge(addr.getSubarchitecture(), 1L, Long::sum);
    cast.v1.Entry entry;
    if (op == cast.v1.Operation.OPERATION_DELETE) {
      entry = entries.remove(key(addr));
    } else {
      entry =
          cast.v1.Entry.newBuilder()
              .setAddress(addr)
              .setType(Types.typeOf(value))
              .setValue(value)
              .setVersion(version)
              .setAuthor(who)
              .setRevision(rev)
              .setModified(Timestamp.newBuilder().setSeconds(1_700_000_000L))
              .build();
      entries.put(key(addr), entry);
    }
    return ChangeEvent.newBuilder()
        .setRevision(rev)
        .setOperation(op)
        .setAddress(addr)
        .setType(Types.typeOf(value))
        .setSourceComponent(who)
        .setVersion(version)
        .setEntry(entry)
        .build();
  }

  private boolean lockedByOther(EntryAddress a) {
    String holder = lockHolders.get(key(a));
    return holder != null && !holder.equals(CALLER.get());
  }

  final class Wm extends WorkingMemoryGrpc.WorkingMemoryImplBase {
    @Override
    public void add(AddRequest req, StreamObserver<WriteResponse> obs) {
      calls.add("Add " + key(req.getAddress()));
      ChangeEvent e;
      synchronized (entries) {
        if (entries.containsKey(key(req.getAddress()))) {
          fail(obs, Status.ALREADY_EXISTS, "entry '" + req.getAddress().getId() + "' already exists");
          return;
        }
        e = write(cast.v1.Operation.OPERATION_ADD, req.getAddress(), req.getValue(), 0);
      }
      publish(List.of(e));
      obs.onNext(WriteResponse.newBuilder().setRevision(e.getRevision()).setVersion(0).build());
      obs.onCompleted();
    }

    @Override
    public void overwrite(OverwriteRequest req, StreamObserver<WriteResponse> obs) {
      calls.add("Overwrite " + key(req.getAddress()));
      ChangeEvent e;
      synchronized (entries) {
        cast.v1.Entry old = entries.get(key(req.getAddress()));
        if (old == null) {
          fail(obs, Status.NOT_FOUND, "no entry '" + req.getAddress().getId() + "'");
          return;
        }
        if (req.hasExpectedVersion() && req.getExpectedVersion() != old.getVersion()) {
          fail(obs, Status.ABORTED, "version " + old.getVersion() + ", not " + req.getExpectedVersion());
          return;
        }
        if (lockedByOther(req.getAddress())) {
          fail(obs, Status.FAILED_PRECONDITION, "locked by " + lockHolders.get(key(req.getAddress())));
          return;
        }
        e = write(cast.v1.Operation.OPERATION_OVERWRITE, req.getAddress(), req.getValue(), old.getVersion() + 1);
      }
      publish(List.of(e));
      obs.onNext(WriteResponse.newBuilder().setRevision(e.getRevision()).setVersion(e.getVersion()).build());
      obs.onCompleted();
    }

    @Override
    public void delete(DeleteRequest req, StreamObserver<WriteResponse> obs) {
      calls.add("Delete " + key(req.getAddress()));
      ChangeEvent e;
      synchronized (entries) {
        cast.v1.Entry old = entries.get(key(req.getAddress()));
        if (old == null) {
          fail(obs, Status.NOT_FOUND, "no entry '" + req.getAddress().getId() + "'");
          return;
        }
        if (req.hasExpectedVersion() && req.getExpectedVersion() != old.getVersion()) {
          fail(obs, Status.ABORTED, "version " + old.getVersion() + ", not " + req.getExpectedVersion());
          return;
        }
        e = write(cast.v1.Operation.OPERATION_DELETE, req.getAddress(), old.getValue(), old.getVersion());
      }
      publish(List.of(e));
      obs.onNext(WriteResponse.newBuilder().setRevision(e.getRevision()).setVersion(e.getVersion()).build());
      obs.onCompleted();
    }

    @Override
    public void get(GetRequest req, StreamObserver<GetResponse> obs) {
      calls.add("Get " + key(req.getAddress()));
      cast.v1.Entry e = entries.get(key(req.getAddress()));
      if (e == null) {
        fail(obs, Status.NOT_FOUND, "no entry '" + req.getAddress().getId() + "'");
        return;
      }
      obs.onNext(GetResponse.newBuilder().setEntry(e).build());
      obs.onCompleted();
    }

    @Override
    public void getByType(GetByTypeRequest req, StreamObserver<GetByTypeResponse> obs) {
      calls.add("GetByType " + req.getSubarchitecture() + "/" + req.getType());
      List<cast.v1.Entry> found = new ArrayList<>();
      synchronized (entries) {
        for (cast.v1.Entry e : entries.values()) {
          if (e.getType().equals(req.getType()) && e.getAddress().getSubarchitecture().equals(req.getSubarchitecture())) {
            found.add(e);
          }
        }
      }
      found.sort((a, b) -> Long.compare(b.getRevision(), a.getRevision()));
      obs.onNext(GetByTypeResponse.newBuilder().addAllEntries(found).build());
      obs.onCompleted();
    }

    @Override
    public void exists(ExistsRequest req, StreamObserver<ExistsResponse> obs) {
      calls.add("Exists " + key(req.getAddress()));
      obs.onNext(ExistsResponse.newBuilder().setExists(entries.containsKey(key(req.getAddress()))).build());
      obs.onCompleted();
    }

    @Override
    public void lock(LockRequest req, StreamObserver<LockResponse> obs) {
      calls.add("Lock " + key(req.getAddress()) + " " + req.getMode() + (req.getNoWait() ? " nowait" : ""));
      if (lockedByOther(req.getAddress())) {
        // The fake never waits: a blocking lock on a held entry runs into its deadline.
        if (req.getNoWait()) {
          fail(obs, Status.FAILED_PRECONDITION, "locked by " + lockHolders.get(key(req.getAddress())));
        }
        return;
      }
      lockHolders.put(key(req.getAddress()), CALLER.get());
      obs.onNext(LockResponse.newBuilder().setDepth(1).build());
      obs.onCompleted();
    }

    @Override
    public void unlock(UnlockRequest req, StreamObserver<UnlockResponse> obs) {
      calls.add("Unlock " + key(req.getAddress()));
      if (!CALLER.get().equals(lockHolders.get(key(req.getAddress())))) {
        fail(obs, Status.FAILED_PRECONDITION, "not locked by " + CALLER.get());
        return;
      }
      lockHolders.remove(key(req.getAddress()));
      obs.onNext(UnlockResponse.newBuilder().setDepth(0).build());
      obs.onCompleted();
    }

    @Override
    public StreamObserver<WatchRequest> watch(StreamObserver<WatchResponse> obs) {
      WatchStream s = new WatchStream(obs);
      watchStreams.add(s);
      return s;
    }
  }

  // ----------------------------------------------------------- TaskManager

  final class Tm extends TaskManagerGrpc.TaskManagerImplBase {
    @Override
    public void propose(ProposeRequest req, StreamObserver<ProposeResponse> obs) {
      cast.v1.Task task =
          cast.v1.Task.newBuilder()
              .setTaskId("t" + tasks.incrementAndGet())
              .setName(req.getName())
              .setComponent(CALLER.get())
              .setData(req.getData())
              .setPriority(req.getPriority())
              .setState(cast.v1.TaskState.TASK_STATE_WAITING)
              .build();
      obs.onNext(ProposeResponse.newBuilder().setTask(task).build());
      obs.onCompleted();
      // "always": adopt at once; "reject-me" tests the other hook.
      var decided =
          task.toBuilder()
              .setState(
                  req.getName().equals("reject-me")
                      ? cast.v1.TaskState.TASK_STATE_REJECTED
                      : cast.v1.TaskState.TASK_STATE_ADOPTED)
              .build();
      for (var d : decisionStreams) {
        synchronized (d) {
          d.onNext(decided);
        }
      }
    }

    @Override
    public void complete(CompleteRequest req, StreamObserver<CompleteResponse> obs) {
      calls.add("Complete " + req.getTaskId() + " " + req.getOutcome() + " " + req.getReason());
      obs.onNext(CompleteResponse.getDefaultInstance());
      obs.onCompleted();
    }

    @Override
    public void retract(RetractRequest req, StreamObserver<RetractResponse> obs) {
      calls.add("Retract " + req.getTaskId());
      obs.onNext(RetractResponse.getDefaultInstance());
      obs.onCompleted();
    }

    @Override
    public void decisions(DecisionsRequest req, StreamObserver<cast.v1.Task> obs) {
      decisionStreams.add(obs);
    }
  }
}
