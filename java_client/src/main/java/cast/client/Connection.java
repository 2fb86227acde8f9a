package cast.client;

/**
 * A plain program's connection to a working memory system (a script, a tool, a
 * notebook), from {@link Cast#connect()}:
 *
 * <pre>
 * try (Connection wm = Cast.connect()) {
 *   wm.onChange(Filters.localTypeFilter(Greeting.class), change -&gt; ...);
 *   wm.add(wm.newId(), greeting);
 * }
 * </pre>
 *
 * <p>It has the working-memory calls, errors and watches of an unmanaged component
 * with the same names ({@code newId}, {@code add}, {@code overwrite}, {@code deleteEntry},
 * {@code addAsync}, {@code overwriteAsync}, {@code get}, {@code getEntry}, {@code getAll},
 * {@code exists}, {@code lock}, {@code tryLock}, {@code unlock}, {@code batch}, {@code onChange});
 * callbacks run on its dispatcher thread. It has no lifecycle: nothing calls {@code configure}, {@code start},
 * {@code run} or {@code stop}. {@link #close()} runs the callbacks already queued, then
 * ends its session (releasing its locks) and closes its channels.
 */
public final class Connection extends UnmanagedComponent {
  /**
   * Binds to {@code transport} and starts the session (reported RUNNING at once: nothing
   * else will run); {@code verify} refuses an identity the options contradict.
   */
  Connection(Transport transport, java.util.function.Consumer<Identity> verify) {
    bind(transport, verify);
    setState(ComponentState.RUNNING);
  }
}
