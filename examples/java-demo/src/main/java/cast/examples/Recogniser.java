package cast.examples;

import static cast.client.Filters.localTypeFilter;

import cast.client.Args;
import cast.client.CastError;
import cast.client.Entry;
import cast.client.LockGuard;
import cast.client.LockMode;
import cast.client.ManagedComponent;
import cast.client.NotFoundError;
import cast.client.Operation;
import cast.client.Task;
import cast.client.TaskOutcome;
import cast.client.WorkingMemoryChange;
import com.google.protobuf.Descriptors.FieldDescriptor;
import java.time.Duration;
import java.util.HashSet;
import java.util.Locale;
import java.util.Set;
import java.util.concurrent.ExecutorService;
import java.util.concurrent.Executors;
import java.util.concurrent.LinkedBlockingQueue;
import java.util.concurrent.ScheduledExecutorService;
import java.util.concurrent.ThreadFactory;
import java.util.concurrent.ThreadPoolExecutor;
import java.util.concurrent.TimeUnit;
import java.util.concurrent.atomic.AtomicInteger;

/**
 * Base of the demo's recognisers, as {@code cast_examples.vision.Recogniser} in Python: one
 * task per new region, run by a small pool of workers.
 *
 * <p>Args: {@code work_ms} (how long recognising takes), {@code retry_ms} (wait before
 * proposing a rejected task again).
 */
public abstract class Recogniser extends ManagedComponent {
  private final String feature;
  private final FieldDescriptor field;
  private long workMs;
  private long retryMs;
  private ThreadPoolExecutor pool;
  private ScheduledExecutorService timers;
  private final Set<String> proposed = new HashSet<>(); // guarded by itself

  /** A recogniser that fills in {@code feature}, a string field of SceneObject ("colour", "shape"). */
  protected Recogniser(String feature) {
    this.feature = feature;
    this.field = SceneObject.getDescriptor().findFieldByName(feature);
    if (field == null) {
      throw new IllegalArgumentException("SceneObject has no field '" + feature + "'");
    }
  }

  /** Fill in the feature on {@code region}; return its name. */
  protected abstract String recognise(SceneObject.Builder region);

  /** Read timings. */
  @Override
  public void configure(Args args) {
    workMs = Math.round(args.getDouble("work_ms", 300));
    retryMs = Math.round(args.getDouble("retry_ms", 700));
    pool = new ThreadPoolExecutor(2, 2, 0, TimeUnit.MILLISECONDS, new LinkedBlockingQueue<>(),
        threads(feature + "-worker"));
    timers = Executors.newSingleThreadScheduledExecutor(threads(feature + "-retry"));
  }

  /** Watch for new regions in the own SA, then take on those already there (a segmenter may be quicker). */
  @Override
  public void start() {
    onChange(localTypeFilter(SceneObject.class, Operation.ADD), this::newRegion);
    for (Entry<SceneObject> entry : getAll(SceneObject.class)) {
      if (!known(entry.value())) {
        proposeOnce(entry.id());
      }
    }
  }

  /** Whether the region already has this recogniser's feature. */
  protected boolean known(SceneObject region) {
    return !((String) region.getField(field)).isEmpty();
  }

  /** Propose to recognise a new region. */
  private void newRegion(WorkingMemoryChange change) {
    proposeOnce(change.id());
  }

  /** Propose a region's first task (the watch and the start-up read may both see it). */
  private void proposeOnce(String objectId) {
    synchronized (proposed) {
      if (!proposed.add(objectId)) {
        return;
      }
    }
    propose(objectId);
  }

  /** Propose the task for one region. */
  private void propose(String objectId) {
    if (isRunning()) {
      String shortId = objectId.substring(objectId.lastIndexOf(':') + 1);
      proposeTask(feature + " " + shortId,
          RecognitionRequest.newBuilder().setObjectId(objectId).setFeature(feature).build());
    }
  }

  /** Recognise on a worker, so that two adopted tasks run at once. */
  @Override
  public void taskAdopted(Task task) {
    pool.execute(() -> work(task));
  }

  /** The queue was full: try again a little later. */
  @Override
  public void taskRejected(Task task) {
    RecognitionRequest request = task.data(RecognitionRequest.class);
    if (request != null) {
      timers.schedule(() -> {
        try {
          propose(request.getObjectId());
        } catch (CastError e) {
          log().warning("proposing " + feature + " of " + request.getObjectId() + " again failed: " + e);
        }
      }, retryMs, TimeUnit.MILLISECONDS);
    }
  }

  private void work(Task task) {
    RecognitionRequest request = task.data(RecognitionRequest.class);
    long started = System.nanoTime();
    try {
      Thread.sleep(workMs); // the expensive part, as far as the task manager knows
    } catch (InterruptedException e) {
      Thread.currentThread().interrupt();
      return;
    }
    String label;
    String name;
    try (LockGuard guard = lock(request.getObjectId(), LockMode.O, Duration.ofSeconds(5))) {
      SceneObject.Builder region = get(request.getObjectId(), SceneObject.class).toBuilder();
      name = recognise(region);
      label = region.getLabel();
      overwrite(request.getObjectId(), region.build());
    } catch (NotFoundError e) {
      taskComplete(task, TaskOutcome.ABANDONED, "the region is gone");
      return;
    } catch (CastError e) {
      taskComplete(task, TaskOutcome.FAILED, e.getMessage());
      return;
    }
    taskComplete(task, TaskOutcome.SUCCEEDED, name);
    double seconds = (System.nanoTime() - started) / 1e9;
    System.out.println(String.format(Locale.ROOT, "%s is %s (%s, %.1f s)", label, name, task.taskId(), seconds));
  }

  /** Let running work finish (work still queued is dropped). */
  @Override
  public void stop() throws InterruptedException {
    timers.shutdownNow();
    pool.shutdown();
    pool.getQueue().clear();
    pool.awaitTermination(30, TimeUnit.SECONDS);
  }

  private static ThreadFactory threads(String prefix) {
    AtomicInteger count = new AtomicInteger();
    return runnable -> {
      Thread thread = new Thread(runnable, prefix + "-" + count.incrementAndGet());
      thread.setDaemon(true);
      return thread;
    };
  }
}
