package cast.itest;

import cast.client.Args;
import cast.client.UnmanagedComponent;

/** Fails in the hook named by its "fail" argument (configure, start, run or stop), for the runner's exit status. */
public class Failing extends UnmanagedComponent {
  private String where = "";

  @Override
  public void configure(Args args) {
    where = args.getString("fail", "");
    check("configure");
  }

  @Override
  public void start() {
    check("start");
  }

  @Override
  public void run() throws Exception {
    check("run");
    waitForStop();
  }

  @Override
  public void stop() {
    System.out.println("stop called");
    System.out.flush();
    check("stop");
  }

  private void check(String hook) {
    if (where.equals(hook)) {
      throw new IllegalStateException("failing in " + hook + " on purpose");
    }
  }
}
