package cast.client;

import com.google.protobuf.ByteString;
import java.lang.reflect.Field;
import java.lang.reflect.Method;
import java.nio.ByteBuffer;
import java.nio.MappedByteBuffer;
import java.util.Map;
import java.util.TreeMap;
import java.util.concurrent.atomic.AtomicInteger;
import java.util.concurrent.atomic.AtomicLong;
import java.util.concurrent.locks.ReentrantReadWriteLock;

/**
 * A session's staging area (docs/client-protocol.md, "Writing a large value"): the memory file
 * the server made for this client, mapped read-write, and which regions of it hold values of
 * writes not answered yet. Regions are whole 4 KiB pages, taken first fit. A write whose
 * outcome is unknown (its stream broke, its deadline passed) may still be applied later, and
 * the server would then copy whatever its region holds: such a region is never written again
 * while the session lives. A {@link Loan} is <em>lent</em> a region instead ({@link #lend}): its
 * header written there, its payload filled by the user in place; while a loan lives (until it is
 * written or closed) the area stays mapped, even once the session ended, since the user's buffer
 * is that memory. Part of {@link SharedSession}.
 */
final class ShmStaging {
  static final int PAGE = 4096;

  /** The boundary a loan's payload starts on within the area: a cache line, as the server's arena aligns it. */
  static final int PAYLOAD_ALIGNMENT = 64;

  /** A region holding one value, until its write's reply came. */
  record Staged(long offset, long size, long taken) {}

  /**
   * A region lent to a loan: {@code region} as taken (what is freed or kept, the pad included),
   * the value in it at {@code offset} (after a pad of less than {@link #PAYLOAD_ALIGNMENT} bytes,
   * so that its payload starts on a multiple of it), {@code size} bytes long (header and
   * payload), and the payload's place, writable ({@code payload}).
   */
  record Lent(Staged region, long offset, long size, ByteBuffer payload) {}

  private final MappedByteBuffer area;
  private final long size;
  // Copies share the lock, the end takes it alone: the area is never unmapped under a copy.
  private final ReentrantReadWriteLock mapping = new ReentrantReadWriteLock();
  private final TreeMap<Long, Long> free = new TreeMap<>(); // offset -> run length; guarded by this
  private long quarantined; // guarded by this
  private boolean closed; // guarded by mapping's write lock
  private boolean unmapped; // guarded by mapping's write lock
  // Loans whose buffer is in the area: it is not unmapped while one lives (their user writes there).
  private final AtomicInteger lent = new AtomicInteger();
  /** Values copied into the area ({@link #stage}; a loan's are not: for tests and diagnostics). */
  final AtomicLong copiedIn = new AtomicLong();

  ShmStaging(MappedByteBuffer area) {
    this.area = area;
    this.size = area.capacity();
    free.put(0L, size);
  }

  /** {@code size} rounded up to whole pages (at least one). */
  static long roundUp(long size) {
    return Math.max(PAGE, (size + PAGE - 1) / PAGE * PAGE);
  }

  /** {@code value} copied into a free region; null when there is none or the area is gone (send the bytes). */
  Staged stage(ByteString value) {
    long taken = roundUp(value.size());
    Long offset = take(taken);
    if (offset == null) {
      return null;
    }
    mapping.readLock().lock();
    try {
      if (closed) {
        return null;
      }
      ByteBuffer to = area.duplicate();
      to.position((int) (long) offset);
      value.copyTo(to);
      copiedIn.incrementAndGet();
    } finally {
      mapping.readLock().unlock();
    }
    return new Staged(offset, value.size(), taken);
  }

  /**
   * A region for a loan's value: {@code header} written in it, then room for {@code size} bytes of
   * payload starting on a multiple of {@link #PAYLOAD_ALIGNMENT} within the area; null when there
   * is no room or the area is gone (the loan is then private memory). The area stays mapped until
   * the loan is {@link #handOver handed over} or {@link #giveBack given back}.
   */
  Lent lend(ByteString header, int size) {
    // Regions start on a page, a multiple of the alignment: the pad depends on the header alone.
    int pad = (PAYLOAD_ALIGNMENT - header.size() % PAYLOAD_ALIGNMENT) % PAYLOAD_ALIGNMENT;
    long length = (long) header.size() + size;
    long taken = roundUp(pad + length);
    Long offset = take(taken);
    if (offset == null) {
      return null;
    }
    Staged region = new Staged(offset, pad + length, taken);
    mapping.readLock().lock(); // close() waits: it sees this loan counted, or this sees it closed
    try {
      if (closed) {
        unstage(region, true);
        return null;
      }
      lent.incrementAndGet();
      ByteBuffer to = area.duplicate();
      to.position((int) (offset + pad));
      header.copyTo(to);
      ByteBuffer payload = area.duplicate();
      payload.position((int) (offset + pad + header.size())).limit((int) (offset + pad + length));
      return new Lent(region, offset + pad, length, payload.slice());
    } finally {
      mapping.readLock().unlock();
    }
  }

  /** The value of {@code loan}, header and payload, copied out (a write that sends its bytes; still mapped). */
  ByteString copy(Lent loan) {
    return ByteString.copyFrom(bytes(loan.offset(), loan.size()));
  }

  /** {@code length} bytes of the area from {@code offset}, read-only, not copied (a loan's value; tests). */
  ByteBuffer bytes(long offset, long length) {
    return area.asReadOnlyBuffer().position((int) offset).limit((int) (offset + length)).slice();
  }

  /** A loan not written: its region is free again. */
  void giveBack(Lent loan) {
    unstage(loan.region(), true);
    loanEnded();
  }

  /**
   * A loan written in place: its region is the write's now, freed or kept after the reply as a
   * staged value's ({@link #unstage}); this side reads it no more.
   */
  void handOver(Lent loan) {
    loanEnded();
  }

  /** Loans whose buffer is in the area (not yet written or closed). */
  int loans() {
    return lent.get();
  }

  /** The area's size in bytes. */
  long size() {
    return size;
  }

  private void loanEnded() {
    if (lent.decrementAndGet() == 0) {
      mapping.writeLock().lock();
      try {
        unmapIfDone();
      } finally {
        mapping.writeLock().unlock();
      }
    }
  }

  /** Unmap the area once it is closed and no loan's buffer is in it (holding mapping's write lock). */
  private void unmapIfDone() {
    if (closed && !unmapped && lent.get() == 0) {
      unmapped = true;
      unmap(area);
    }
  }

  private synchronized Long take(long taken) {
    for (Map.Entry<Long, Long> run : free.entrySet()) {
      if (run.getValue() >= taken) {
        long offset = run.getKey();
        free.remove(offset);
        if (run.getValue() > taken) {
          free.put(offset + taken, run.getValue() - taken);
        }
        return offset;
      }
    }
    return null;
  }

  /** The write's reply came ({@code known}): the region is free again; else it stays taken for good. */
  synchronized void unstage(Staged staged, boolean known) {
    if (!known) {
      quarantined += staged.taken();
      return;
    }
    long offset = staged.offset();
    long length = staged.taken();
    Map.Entry<Long, Long> before = free.floorEntry(offset);
    if (before != null && before.getKey() + before.getValue() == offset) {
      free.remove(before.getKey());
      offset = before.getKey();
      length += before.getValue();
    }
    Long after = free.get(offset + length);
    if (after != null) {
      free.remove(offset + length);
      length += after;
    }
    free.put(offset, length);
  }

  /** Bytes of regions kept because their write's outcome is unknown. */
  synchronized long quarantined() {
    return quarantined;
  }

  /** Bytes free now. */
  synchronized long freeBytes() {
    return free.values().stream().mapToLong(Long::longValue).sum();
  }

  /**
   * The session ended: unmap the area, or once the last loan whose buffer is in it was written or
   * closed; later stages and loans get null.
   */
  void close() {
    mapping.writeLock().lock();
    try {
      closed = true;
      unmapIfDone();
    } finally {
      mapping.writeLock().unlock();
    }
  }

  /**
   * Unmap a mapping now, rather than when the garbage collector finds it (which may be long
   * after, and keeps the memory file alive meanwhile). Only for a mapping nothing reads any
   * more: the staging area once the session ended and no loan's buffer is in it, a retired
   * segment once no lease of it is held. Without sun.misc.Unsafe (a JVM that lacks it) the
   * collector does it.
   */
  static void unmap(MappedByteBuffer buffer) {
    try {
      Class<?> unsafe = Class.forName("sun.misc.Unsafe");
      Field the = unsafe.getDeclaredField("theUnsafe");
      the.setAccessible(true);
      Method invokeCleaner = unsafe.getMethod("invokeCleaner", ByteBuffer.class);
      invokeCleaner.invoke(the.get(null), buffer);
    } catch (ReflectiveOperationException | RuntimeException e) {
      // Left to the garbage collector.
    }
  }
}
