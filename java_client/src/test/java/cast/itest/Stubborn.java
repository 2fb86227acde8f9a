package cast.itest;

import cast.client.UnmanagedComponent;

/** Its stop() does not return in time: the orchestrator asks for a thread dump (SIGQUIT), then kills it. */
public class Stubborn extends UnmanagedComponent {
  @Override
  public void stop() throws InterruptedException {
    Thread.sleep(600_000);
  }
}
