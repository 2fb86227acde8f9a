package cast.client;

import cast.v1.RegisterRequest;
import java.io.IOException;
import java.io.InputStream;
import java.io.UncheckedIOException;
import java.util.Properties;

/**
 * The release of the library and the wire API it speaks. The release is the repository's VERSION
 * file (Maven writes it into {@code cast/client/library.properties}); the library sends it in its
 * session registration, and {@code cast components} shows it.
 */
public final class Version {
  private static final String LIBRARY = load();

  private Version() {}

  /** The release of the library on the class path ("0.1.0"). */
  public static String library() {
    return LIBRARY;
  }

  /** The wire API the library speaks: the protobuf package of its generated code ("cast.v1"). */
  public static String wireApi() {
    return RegisterRequest.getDescriptor().getFile().getPackage();
  }

  private static String load() {
    try (InputStream in = Version.class.getResourceAsStream("library.properties")) {
      if (in == null) {
        throw new IllegalStateException("cast/client/library.properties is missing from the class path: "
            + "the cast-client jar is incomplete; build it with Maven (make java)");
      }
      Properties properties = new Properties();
      properties.load(in);
      return properties.getProperty("version", "unknown");
    } catch (IOException e) {
      throw new UncheckedIOException(e);
    }
  }
}
