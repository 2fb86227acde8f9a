package cast.client;

import java.io.IOException;
import java.nio.charset.StandardCharsets;
import java.nio.file.Files;
import java.nio.file.Path;
import java.nio.file.attribute.BasicFileAttributes;

/**
 * The component's current token: fixed, or re-read from the file the
 * orchestrator renews (CAST_TOKEN_FILE). The file is checked at most once a
 * second (one stat) and re-read only when its modification time or size
 * changed; an empty or unreadable file keeps the last token
 * (docs/client-protocol.md, "Security").
 */
final class TokenSource {
  private final Path path;
  private final long checkIntervalNanos;
  private String token; // guarded by this
  private long checked; // guarded by this
  private String stamp; // guarded by this

  TokenSource(String token, Path path) {
    this(token, path, 1_000_000_000L);
  }

  TokenSource(String token, Path path, long checkIntervalNanos) {
    this.token = token;
    this.path = path;
    this.checkIntervalNanos = checkIntervalNanos;
    if (path != null) {
      reload(true);
    }
  }

  private synchronized void reload(boolean force) {
    long now = System.nanoTime();
    if (!force && now - checked < checkIntervalNanos) {
      return;
    }
    checked = now;
    try {
      BasicFileAttributes a = Files.readAttributes(path, BasicFileAttributes.class);
      String s = a.lastModifiedTime().toMillis() + ":" + a.lastModifiedTime().toInstant().getNano() + ":" + a.size();
      if (!s.equals(stamp)) {
        String text = Files.readString(path, StandardCharsets.UTF_8).trim();
        if (!text.isEmpty()) {
          token = text;
        }
        stamp = s;
      }
    } catch (IOException e) {
      // keep the last token: the orchestrator may be replacing the file right now
    }
  }

  /** The token to send now. */
  String token() {
    if (path != null) {
      reload(false);
    }
    synchronized (this) {
      return token;
    }
  }

  /** Re-read the file at once (the server refused the token); true if the token changed. */
  boolean refresh() {
    if (path == null) {
      return false;
    }
    String before;
    synchronized (this) {
      before = token;
    }
    reload(true);
    synchronized (this) {
      return !token.equals(before);
    }
  }
}
