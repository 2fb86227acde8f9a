package cast.client;

import com.google.protobuf.ByteString;
import java.lang.reflect.Field;
import java.lang.reflect.Method;
import java.nio.ByteBuffer;
import java.nio.MappedByteBuffer;
import java.util.Map;
import java.util.TreeMap;
import java.util.concurrent.locks.ReentrantReadWriteLock;

/**
 * A session's staging area (docs/client-protocol.md, "Writing a large value"): the memory file
 * the server made for this client, mapped read-write, and which regions of it hold values of
 * writes not answered yet. Regions are whole 4 KiB pages, taken first fit. A write whose
 * outcome is unknown (its stream broke, its deadline passed) may still be applied later, and
 * the server would then copy whatever its region holds: such a region is never written again
 * while the session lives. Part of {@link SharedSession}.
 */
final class ShmStaging {
  static final int PAGE = 4096;

  /** A region holding one value, until its write's reply came. */
  record Staged(long offset, long size, long taken) {}

  private final MappedByteBuffer area;
  private final long size;
  // Copies share the lock, the end takes it alone: the area is never unmapped under a copy.
  private final ReentrantReadWriteLock mapping = new ReentrantReadWriteLock();
  private final TreeMap<Long, Long> free = new TreeMap<>(); // offset -> run length; guarded by this
  private long quarantined; // guarded by this
  private boolean closed; // guarded by mapping's write lock

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
    } finally {
      mapping.readLock().unlock();
    }
    return new Staged(offset, value.size(), taken);
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

  /** Unmap the area (the session ended); later stages get null. */
  void close() {
    mapping.writeLock().lock();
    try {
      if (!closed) {
        closed = true;
        unmap(area);
      }
    } finally {
      mapping.writeLock().unlock();
    }
  }

  /**
   * Unmap a mapping now, rather than when the garbage collector finds it (which may be long
   * after, and keeps the memory file alive meanwhile). Only for a mapping nothing reads any
   * more: the staging area once the session ended, a retired segment once no lease of it is
   * held. Without sun.misc.Unsafe (a JVM that lacks it) the collector does it.
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
