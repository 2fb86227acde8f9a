package cast.client;

import static org.junit.jupiter.api.Assertions.*;

import java.lang.reflect.Constructor;
import java.lang.reflect.Executable;
import java.lang.reflect.Field;
import java.lang.reflect.Method;
import java.lang.reflect.Modifier;
import java.lang.reflect.Type;
import java.net.URISyntaxException;
import java.nio.file.Files;
import java.nio.file.Path;
import java.util.ArrayList;
import java.util.List;
import java.util.Set;
import java.util.TreeSet;
import java.util.stream.Stream;
import org.junit.jupiter.api.Test;

/**
 * The generated {@code cast.v1} classes are the wire's, not the library's: no public
 * class of {@code cast.client} shows one in a public or protected signature, and none
 * has a {@code toProto}/{@code fromProto} (conversions live in the package-private
 * {@link Conversions}). Users see only library types and protobuf's own.
 */
class PublicApiTest {
  /** Every class of the library's main classes in package cast.client that users can see. */
  static List<Class<?>> publicClasses() throws Exception {
    Path root = Path.of(Component.class.getProtectionDomain().getCodeSource().getLocation().toURI());
    List<Class<?>> out = new ArrayList<>();
    try (Stream<Path> files = Files.list(root.resolve("cast/client"))) {
      for (Path f : files.filter(p -> p.toString().endsWith(".class")).sorted().toList()) {
        String name = "cast.client." + f.getFileName().toString().replace(".class", "");
        Class<?> c = Class.forName(name, false, PublicApiTest.class.getClassLoader());
        if (visible(c)) {
          out.add(c);
        }
      }
    }
    return out;
  }

  /** Public, and so are the classes it is nested in. */
  static boolean visible(Class<?> c) {
    for (Class<?> k = c; k != null; k = k.getEnclosingClass()) {
      if (!Modifier.isPublic(k.getModifiers()) || k.isAnonymousClass() || k.isLocalClass()) {
        return false;
      }
    }
    return true;
  }

  static boolean exposed(int modifiers) {
    return Modifier.isPublic(modifiers) || Modifier.isProtected(modifiers);
  }

  /** What each exposed member of {@code c} says about wire types: "Class.member: type" per offence. */
  static List<String> offences(Class<?> c) {
    List<String> out = new ArrayList<>();
    List<Type> supers = new ArrayList<>(List.of(c.getGenericInterfaces()));
    if (c.getGenericSuperclass() != null) {
      supers.add(c.getGenericSuperclass());
    }
    for (Type t : supers) {
      check(out, c.getName() + " extends", t);
    }
    List<Executable> members = new ArrayList<>();
    for (Method m : c.getDeclaredMethods()) {
      if (exposed(m.getModifiers()) && !m.isSynthetic()) {
        members.add(m);
        if (m.getName().equals("toProto") || m.getName().equals("fromProto")) {
          out.add(c.getName() + "." + m.getName() + ": a conversion in the public API");
        }
        check(out, c.getName() + "." + m.getName() + " returns", m.getGenericReturnType());
      }
    }
    for (Constructor<?> k : c.getDeclaredConstructors()) {
      if (exposed(k.getModifiers())) {
        members.add(k);
      }
    }
    for (Executable e : members) {
      for (Type t : e.getGenericParameterTypes()) {
        check(out, c.getName() + "." + e.getName() + " takes", t);
      }
    }
    for (Field f : c.getDeclaredFields()) {
      if (exposed(f.getModifiers())) {
        check(out, c.getName() + "." + f.getName(), f.getGenericType());
      }
    }
    return out;
  }

  private static void check(List<String> out, String where, Type t) {
    // The type name spells out type arguments too (List<cast.v1.Entry>).
    if (t.getTypeName().contains("cast.v1.")) {
      out.add(where + " " + t.getTypeName());
    }
  }

  /**
   * The library's public types: what docs/java.md documents. The machinery (transport, streams,
   * sessions, shared memory, conversions, the status-code table, schema registration) stays
   * package-private, so that a user's IDE offers only these.
   */
  static final Set<String> API =
      Set.of(
          "AlreadyExistsError", "Args", "Batch", "Cast", "CastError", "ChangeCallback", "ChangeFilter",
          "ClientTls", "Component", "ConnectOptions", "Connection", "ConsistencyError",
          "DeadlineExceededError", "Delivery", "Entry", "Filters", "HistoryExpiredError", "Identity",
          "InternalError", "InvalidArgumentError", "LaunchContract", "LockGuard", "LockMode",
          "LockedError", "Loan", "ManagedComponent", "NoSessionError", "NotFoundError", "Operation",
          "PermissionDeniedError", "Priority", "ResourceExhaustedError", "Runner", "SchemaConflictError",
          "Task", "TaskOutcome", "TaskState", "TaskStateError", "Tokens", "Types",
          "UnauthenticatedError", "UnavailableError", "UnmanagedComponent", "ValueView", "Version",
          "WatchHandle", "WatchOptions", "WorkingMemoryAddress", "WorkingMemoryChange", "WriteResult");

  @Test
  void onlyTheApiIsPublic() throws Exception {
    Set<String> visible = new TreeSet<>();
    for (Class<?> c : publicClasses()) {
      if (c.getEnclosingClass() == null) {
        visible.add(c.getSimpleName());
      }
    }
    Set<String> extra = new TreeSet<>(visible);
    extra.removeAll(API);
    Set<String> missing = new TreeSet<>(API);
    missing.removeAll(visible);
    assertTrue(extra.isEmpty(), "public but not the API (make it package-private, or document it and add it): " + extra);
    assertTrue(missing.isEmpty(), "the API lost: " + missing);
  }

  @Test
  void noPublicSignatureShowsAGeneratedWireType() throws Exception {
    List<Class<?>> classes = publicClasses();
    // The scan must see the library, or it proves nothing.
    assertTrue(classes.contains(Component.class) && classes.contains(Task.class), classes.toString());
    assertTrue(classes.contains(WorkingMemoryChange.class) && classes.contains(ChangeFilter.class));
    assertFalse(classes.contains(Conversions.class) || classes.contains(Transport.class), "package-private");
    List<String> offences = new ArrayList<>();
    for (Class<?> c : classes) {
      offences.addAll(offences(c));
    }
    assertEquals(List.of(), offences);
  }

  /** A class that would break the rule: the check finds what it must. */
  public static final class Offender {
    /** A conversion that must not be public. */
    public cast.v1.Task toProto() {
      return cast.v1.Task.getDefaultInstance();
    }

    /** A wire type in a parameter's type argument. */
    public void take(List<cast.v1.Entry> entries) {}
  }

  @Test
  void theCheckFindsWireTypesWhereverTheyAre() throws URISyntaxException {
    List<String> found = offences(Offender.class);
    assertEquals(3, found.size(), found.toString());
    assertTrue(found.get(0).contains("toProto"), found.toString());
    assertTrue(found.stream().anyMatch(s -> s.contains("takes java.util.List<cast.v1.Entry>")), found.toString());
  }
}
