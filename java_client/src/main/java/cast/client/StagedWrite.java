package cast.client;

import cast.v1.StagedValue;
import cast.v1.WriteReply;
import cast.v1.WriteRequest;
import com.google.protobuf.Any;
import java.time.Duration;
import java.util.ArrayList;
import java.util.List;
import java.util.concurrent.CompletableFuture;
import java.util.concurrent.Executor;

/**
 * The values of one write request (an add, an overwrite, a batch) staged in the shared-memory
 * session with the server it goes to (docs/client-protocol.md, "Writing a large value"): a
 * value of at least the session's threshold is copied into the staging area and named in the
 * request instead of carried; without a session, or without room, it travels as bytes. When
 * the write is over its regions are freed, unless its outcome is unknown (UnavailableError,
 * DeadlineExceededError, an interrupted wait): the server may still apply it and copy whatever
 * the regions then hold, so they stay taken while the session lives. A {@link Loan}'s value is
 * already in the staging area: in the write's session it is named there, its region one of the
 * write's ({@link #stage(Loan)}). Part of the {@code
 * grpc_transport} role, as {@code _fill} and {@code _unstage} are in
 * python/cast/client/grpc_transport.py.
 */
final class StagedWrite {
  private final SharedSession session; // null: every value as bytes
  private final List<ShmStaging.Staged> regions = new ArrayList<>();

  private StagedWrite(SharedSession session) {
    this.session = session;
  }

  /**
   * Staging for a write to {@code server}: its session, opened now (in at most {@code within},
   * the write's time left) if it can be, or none; after a renewed token, the new session the
   * write will go on ({@link SharedLink#writerSession}).
   */
  static StagedWrite to(GrpcServer server, Duration within) {
    SharedLink link = server.shared;
    return new StagedWrite(link == null ? null : link.writerSession(within));
  }

  /** {@code value}'s bytes staged, and what the request says of them; null: send the bytes. */
  StagedValue stage(Any value) {
    if (session == null || value == null || value.getValue().size() < session.threshold) {
      return null;
    }
    ShmStaging.Staged staged = session.stage(value.getValue());
    if (staged == null) {
      return null;
    }
    regions.add(staged);
    return session.stagedValue(staged);
  }

  /** What a write request says of its value: its bytes, or its type alone and where it is staged ({@code staged}). */
  record Value(Any value, StagedValue staged) {}

  /**
   * The value of {@code loan} (spent for this write): named where it is when it is in this
   * write's session, still live, with nothing copied (its region is then this write's, freed or
   * kept after the reply as a staged value's); else its bytes, staged as any value's ({@link
   * #stage(Any)}), and its place in another session (ended, or given way to a renewed token)
   * goes back.
   */
  Value stage(Loan loan) {
    if (session != null && loan.memory() instanceof LoanMemory.InStaging inPlace && inPlace.in(session)) {
      ShmStaging.Lent lent = inPlace.handOver();
      regions.add(lent.region());
      return new Value(Any.newBuilder().setTypeUrl(loan.typeUrl()).build(), session.stagedValue(lent));
    }
    Any value = loan.value();
    return new Value(value, stage(value));
  }

  /** Whether a write that failed with {@code error} may still be applied. */
  static boolean inDoubt(Throwable error) {
    if (error instanceof UnavailableError || error instanceof DeadlineExceededError) {
      return true;
    }
    // An interrupted wait, or a failure that is not the server's answer, knows nothing either.
    return !(error instanceof CastError) || "CANCELLED".equals(((CastError) error).code());
  }

  /**
   * Send {@code request} on {@code stream} and wait for its reply (WriteStream.call) for what is
   * left of {@code budget}; then free or keep regions.
   */
  WriteReply call(WriteStream stream, WriteRequest.Builder request, Budget budget) {
    Duration wait = left(budget);
    Throwable error = null;
    try {
      return stream.call(request, wait);
    } catch (RuntimeException e) {
      error = e;
      throw e;
    } finally {
      done(error);
    }
  }

  /**
   * Send {@code request} without waiting (WriteStream.submitWrite); the regions are freed (or
   * kept) before the returned future completes, so a write its continuation makes finds them free.
   */
  CompletableFuture<WriteResult> submit(
      WriteStream stream, WriteRequest.Builder request, Executor results, Budget budget) {
    Duration wait = left(budget);
    CompletableFuture<WriteResult> sent;
    try {
      sent = stream.submitWrite(request, results, wait);
    } catch (RuntimeException e) {
      done(e);
      throw e;
    }
    CompletableFuture<WriteResult> out = new CompletableFuture<>();
    sent.whenComplete(
        (result, error) -> {
          done(error);
          if (error != null) {
            out.completeExceptionally(error);
          } else {
            out.complete(result);
          }
        });
    return out;
  }

  /** What is left of {@code budget}; when nothing is, the regions are free again (nothing was sent). */
  private Duration left(Budget budget) {
    try {
      return budget.left();
    } catch (DeadlineExceededError e) {
      done(null);
      throw e;
    }
  }

  /** The write is over ({@code error}: null if it succeeded): free its regions unless its outcome is unknown. */
  void done(Throwable error) {
    boolean known = error == null || !inDoubt(error);
    for (ShmStaging.Staged staged : regions) {
      session.unstage(staged, known);
    }
    regions.clear();
  }
}
