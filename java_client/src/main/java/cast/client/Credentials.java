package cast.client;

import io.grpc.CallOptions;
import io.grpc.Channel;
import io.grpc.ChannelCredentials;
import io.grpc.ClientCall;
import io.grpc.ClientInterceptor;
import io.grpc.ForwardingClientCall;
import io.grpc.Metadata;
import io.grpc.MethodDescriptor;
import io.grpc.TlsChannelCredentials;
import java.io.File;
import java.io.IOException;
import java.nio.charset.StandardCharsets;
import java.nio.file.Files;
import java.nio.file.Path;
import java.nio.file.attribute.BasicFileAttributes;

/**
 * What a component's calls carry to prove who it is (docs/client-protocol.md,
 * "Security"): its current token, fixed or re-read from the file the orchestrator
 * renews (CAST_TOKEN_FILE), sent as {@code authorization: Bearer} metadata on every
 * call; and the TLS channel credentials of {@link ClientTls}. The file is checked at
 * most once a second (one stat) and re-read only when its modification time or size
 * changed; an empty or unreadable file keeps the last token. The twin of
 * python/cast/client/credentials.py and cpp_client/src/credentials.cc. The public
 * value types stay on their own: {@link ClientTls} (TLS settings) and {@link Tokens}
 * (minting a token from the system's secret).
 */
final class Credentials {
  private static final Metadata.Key<String> AUTHORIZATION =
      Metadata.Key.of("authorization", Metadata.ASCII_STRING_MARSHALLER);

  private final Path path;
  private final long checkIntervalNanos;
  private String token; // guarded by this
  private long checked; // guarded by this
  private String stamp; // guarded by this

  /** The token {@code token}, renewed through {@code path} when it is not null. */
  Credentials(String token, Path path) {
    this(token, path, 1_000_000_000L);
  }

  Credentials(String token, Path path, long checkIntervalNanos) {
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

  /** Adds the current token to every call (streams too: they are authenticated when opened). */
  ClientInterceptor interceptor() {
    return new ClientInterceptor() {
      @Override
      public <Q, R> ClientCall<Q, R> interceptCall(MethodDescriptor<Q, R> method, CallOptions options, Channel next) {
        return new ForwardingClientCall.SimpleForwardingClientCall<Q, R>(next.newCall(method, options)) {
          @Override
          public void start(Listener<R> listener, Metadata headers) {
            headers.put(AUTHORIZATION, "Bearer " + token());
            super.start(listener, headers);
          }
        };
      }
    };
  }

  /** gRPC channel credentials for {@code tls}; InvalidArgumentError naming a file that cannot be read. */
  static ChannelCredentials channelCredentials(ClientTls tls) {
    try {
      TlsChannelCredentials.Builder b = TlsChannelCredentials.newBuilder().trustManager(new File(tls.ca()));
      if (tls.cert() != null) {
        b.keyManager(new File(tls.cert()), new File(tls.key()));
      }
      return b.build();
    } catch (IOException | RuntimeException e) {
      throw new InvalidArgumentError(
          "cannot read a TLS file (CAST_TLS_CA/CERT/KEY; PEM, the key PKCS#8): " + e.getMessage());
    }
  }
}
