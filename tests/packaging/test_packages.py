"""The three packages as a team uses them, each from a clean directory outside the repository.

- Python: ``python -m build`` makes the sdist and the wheel; the wheel goes into a fresh virtual
  environment (its dependencies from the package index, pip's cache reused), whose ``cast serve``
  is the server of every test here, and whose ``python -m cast.run`` runs the quick start's
  component; with pytest added to it, the quick start's tests pass with the wheel's testing kit
  (its pytest plugin found through the package's entry point).
- C++: ``cmake --install`` of the library ``make cpp`` built, to a temporary prefix;
  ``examples/cpp/hello`` (copied out, so ``../../../cpp_client`` does not exist) is configured
  with ``find_package(cast 0.1 CONFIG REQUIRED COMPONENTS testing)`` against it, built, its
  GoogleTest test run by ctest (cast::testing finding the wheel's ``cast`` on PATH), and run;
  pkg-config's ``cast.pc`` links a program of its own.
- Java: ``examples/java`` (copied out) builds on the cast-bom, cast-client and cast-testing that
  ``make java`` installed into the local Maven repository (``$CAST_TEST_MVN``'s), its JUnit test
  passing against the wheel's ``cast serve``, and its component runs on the class path the build
  wrote (the installed jars, not the tree's cast-client-all.jar), against the wheel's `cast serve`
  of its own system (its greeting.proto is another file than the C++ example's of the same name).

Each out-of-tree test run of the three examples' tests prints what its test framework printed
(``pytest -s`` shows it), the output a release's notes show.

``make package-test`` runs this module after ``make setup proto cpp java``; a missing tool or
build fails the test, it never skips. ``CAST_PACKAGE_TEST_CPP_BUILD`` names another CMake build
directory of cpp_client to install from (default ``build/cpp``).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tarfile
import threading
import venv
import zipfile
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from tests.conftest import ROOT, SECRET, maven, maven_repository, wait_for

VERSION = (ROOT / "VERSION").read_text().strip()
CPP_BUILD = Path(os.environ.get("CAST_PACKAGE_TEST_CPP_BUILD") or ROOT / "build" / "cpp")
PROTOS = sorted(p.stem for p in (ROOT / "proto" / "cast" / "v1").glob("*.proto"))
HELLO_LINES = [f"ADD hello:X:{i + 1} (revision R): hello {i}" for i in range(3)]

pytestmark = pytest.mark.timeout(600)  # builds and installs: minutes on a busy 2-core machine


def tool(name: str, hint: str) -> str:
    found = shutil.which(name)
    if found is None:
        pytest.fail(f"{name} is not installed: {hint}")
    return found


def run(command: list[str], cwd: Path, env: dict[str, str] | None = None, timeout: float = 300) -> str:
    """Run a command that must succeed; its standard output and error, which the failure shows."""
    done = subprocess.run(command, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    output = done.stdout + done.stderr
    assert done.returncode == 0, f"{' '.join(command)} exited {done.returncode} in {cwd}:\n{output[-6000:]}"
    return output


def hello_lines(stdout: str) -> list[str]:
    """The greetings a hello component printed, with its random id part and revisions made fixed."""
    lines = [line.strip() for line in stdout.splitlines() if line.startswith("ADD ")]
    return [re.sub(r"\(revision \d+\)", "(revision R)", re.sub(r":[0-9a-f]{6}:", ":X:", line)) for line in lines]


@dataclass
class Installed:
    """The wheel's virtual environment and the `cast serve` it runs."""

    work: Path
    wheel: Path
    sdist: Path
    build_output: str
    venv: Path
    env: dict[str, str]
    endpoint: str = ""

    def cast(self, *args: str, extra: dict[str, str] | None = None) -> str:
        """The venv's `cast` command; its output (it must succeed)."""
        return run([str(self.venv / "bin" / "cast"), *args], self.work, {**self.env, **(extra or {})}, 120)

    @contextmanager
    def serve(self, config: Path) -> Iterator[str]:
        """The venv's `cast serve CONFIG` on a free port, for the block; its endpoint."""
        server = subprocess.Popen([str(self.venv / "bin" / "cast"), "serve", config.name, "--listen", "127.0.0.1:0"],
                                  cwd=config.parent, env=self.env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                  text=True)
        try:
            assert server.stdout is not None
            first = server.stdout.readline().strip()
            assert first.startswith("listening on "), f"the wheel's cast serve did not start: {first}\n" + \
                server.stdout.read()
            threading.Thread(target=server.stdout.read, daemon=True).start()
            yield first.removeprefix("listening on ")
        finally:
            server.terminate()
            server.wait(20)

    def launch_env(self, component: str, sa: str, args: dict[str, Any] | None = None,
                   endpoint: str = "") -> dict[str, str]:
        """The launch contract of a component started by hand, as `cast token` prints it."""
        contract = json.loads(self.cast("token", component, "--sa", sa, "--endpoint", endpoint or self.endpoint,
                                        "--json"))
        contract["CAST_ARGS"] = json.dumps(args or {})
        return {**self.env, **contract}

    def components(self, endpoint: str = "") -> dict[str, dict[str, Any]]:
        """`cast components --json` of a served system (the quick start's by default), by id."""
        endpoint = endpoint or self.endpoint
        token = json.loads(self.cast("token", "tool", "--sa", "greetings", "--endpoint", endpoint,
                                     "--json"))["CAST_TOKEN"]
        rows = json.loads(self.cast("components", "--json", "--endpoint", endpoint, extra={"CAST_TOKEN": token}))
        return {row["id"]: row for row in rows}


@pytest.fixture(scope="module")
def installed(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Installed]:
    """sdist and wheel built from the tree, the wheel installed into a fresh venv, its `cast serve` running."""
    work = tmp_path_factory.mktemp("packages")
    assert not work.resolve().is_relative_to(ROOT), "the packages must be used outside the repository"
    built = run([sys.executable, "-m", "build", "--outdir", str(work / "dist"), str(ROOT)], work, timeout=600)
    [wheel] = (work / "dist").glob("cast_grpc-*.whl")
    [sdist] = (work / "dist").glob("cast_grpc-*.tar.gz")
    # A venv without its own pip (ensurepip costs seconds): this environment's pip installs into it.
    venv.EnvBuilder(with_pip=False).create(work / "venv")
    # Nothing of the tree's environment: no PYTHONPATH, no CAST_* variables, the venv first on PATH.
    env = {k: v for k, v in os.environ.items() if not k.startswith(("CAST_", "PYTHON", "VIRTUAL_ENV"))}
    env.update(PATH=f"{work / 'venv' / 'bin'}{os.pathsep}{env.get('PATH', '')}", CAST_SECRET=SECRET)
    run([sys.executable, "-m", "pip", "--python", str(work / "venv" / "bin" / "python"), "install", "--quiet",
         str(wheel)], work, env, 600)
    shutil.copytree(ROOT / "examples" / "quickstart", work / "quickstart")
    handle = Installed(work, wheel, sdist, built, work / "venv", env)
    with handle.serve(work / "quickstart" / "system.yaml") as endpoint:
        handle.endpoint = endpoint
        yield handle


# ------------------------------------------------------------------------------------------ Python

def test_the_wheel_and_sdist_hold_the_generated_code_and_current_metadata(installed: Installed) -> None:
    assert "SetuptoolsDeprecationWarning" not in installed.build_output, installed.build_output
    names = set(zipfile.ZipFile(installed.wheel).namelist())
    for stem in PROTOS:
        for suffix in ("_pb2.py", "_pb2.pyi", "_pb2_grpc.py", "_pb2_grpc.pyi"):
            assert f"cast/v1/{stem}{suffix}" in names, f"the wheel lacks cast/v1/{stem}{suffix}"
    assert {"cast/py.typed", "cast/v1/__init__.py", "cast/config/system.schema.json", "cast/VERSION"} <= names
    assert {"cast/testing/__init__.py", "cast/testing/pytest_plugin.py"} <= names
    entry_points = zipfile.ZipFile(installed.wheel).read(f"cast_grpc-{VERSION}.dist-info/entry_points.txt").decode()
    assert "[pytest11]\ncast = cast.testing.pytest_plugin" in entry_points, entry_points
    assert not any(n.startswith("tests/") for n in names)
    metadata = zipfile.ZipFile(installed.wheel).read(f"cast_grpc-{VERSION}.dist-info/METADATA").decode()
    assert f"\nVersion: {VERSION}\n" in metadata
    assert "\nLicense-Expression: BSD-3-Clause\n" in metadata
    assert "\nLicense-File: LICENSE\n" in metadata and f"cast_grpc-{VERSION}.dist-info/licenses/LICENSE" in names
    requires = [line.split(": ", 1)[1] for line in metadata.splitlines() if line.startswith("Requires-Dist: ")]
    assert any(r.startswith("grpcio>=") for r in requires) and any(r.startswith("protobuf>=") for r in requires)
    # Lower bounds only, but for the one package whose 0.x minor releases change its API.
    capped = [r for r in requires if "<" in r.split(";")[0]]
    assert capped == ["foxglove-sdk<0.31,>=0.30"], capped
    with tarfile.open(installed.sdist) as sdist:
        members = {m.name.split("/", 1)[1] for m in sdist.getmembers() if "/" in m.name}
    assert {f"proto/cast/v1/{stem}.proto" for stem in PROTOS} <= members
    assert {f"python/cast/v1/{stem}_pb2.py" for stem in PROTOS} <= members
    assert {"VERSION", "setup.py", "build_support/cast_protos.py", "CHANGELOG.md", "LICENSE"} <= members


def test_the_compiled_wheel_builds_from_a_checkout_that_has_no_generated_code(tmp_path: Path) -> None:
    """docs/packages.md, "The compiled wheel": CAST_MYPYC=1 in a fresh checkout (no python/cast/v1 yet)."""
    checkout = tmp_path / "checkout"
    tracked = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True).stdout
    for name in filter(None, tracked.decode().split("\0")):
        if (ROOT / name).is_file():  # a file deleted in the working tree is not copied
            (checkout / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(ROOT / name, checkout / name)
    assert not (checkout / "python" / "cast" / "v1").exists()
    # An environment with the development requirements and no cast installed (this one's editable
    # install would show mypy the tree's generated code), as the page's commands make it.
    builder = tmp_path / "venv"
    venv.EnvBuilder(with_pip=False).create(builder)
    env = {k: v for k, v in os.environ.items() if not k.startswith(("CAST_", "PYTHON", "VIRTUAL_ENV"))}
    python = str(builder / "bin" / "python")
    run([str(Path(sys.executable).parent / "uv"), "pip", "install", "--quiet", "--python", python,
         "-r", str(checkout / "requirements-dev.txt")], checkout, env, 600)
    # C compiled unoptimised (MYPYC_OPT_LEVEL=0: half the build's CPU): what is tested is that the checkout
    # builds, as the C++ library's subdirectory build is tested (make mypyc builds the optimised wheel).
    run([sys.executable, "-m", "pip", "--python", python, "wheel", "--quiet",
         "--no-build-isolation", "--no-deps", "-w", str(tmp_path / "dist"), "."], checkout,
        {**env, "CAST_MYPYC": "1", "MYPYC_OPT_LEVEL": "0"}, 900)
    [wheel] = (tmp_path / "dist").glob("cast_grpc-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    compiled = {n.split(".", 1)[0] for n in names if n.endswith(".so")}
    assert {"cast/core/access", "cast/server/writes", "cast/wire/shared_memory"} <= compiled, sorted(compiled)
    assert {f"cast/v1/{stem}_pb2.py" for stem in PROTOS} <= names


def test_the_installed_cast_serves_and_runs_the_quick_start(installed: Installed) -> None:
    python = str(installed.venv / "bin" / "python")
    where = run([python, "-c", "import cast, cast.v1.directory_pb2 as d; print(cast.__file__); print(d.__file__)"],
                installed.work, installed.env)
    assert all(Path(line).is_relative_to(installed.venv) for line in where.split()), where
    assert installed.cast("--version").strip() == f"cast {VERSION} (wire API cast.v1)"
    env = {**installed.launch_env("hello", "greetings"), "PYTHONPATH": str(installed.work / "quickstart")}
    out = run([python, "-m", "cast.run", "hello:Hello"], installed.work / "quickstart", env, 120)
    assert hello_lines(out) == HELLO_LINES, out
    hello = installed.components()["hello"]
    assert (hello["language"], hello["library_version"], hello["state"]) == ("python", VERSION, "disconnected")


def test_the_quick_start_tests_pass_with_the_wheels_testing_kit(installed: Installed) -> None:
    python = str(installed.venv / "bin" / "python")
    run([sys.executable, "-m", "pip", "--python", python, "install", "--quiet", "pytest"], installed.work,
        installed.env, 600)
    work = installed.work / "quickstart-tests"
    shutil.copytree(ROOT / "examples" / "quickstart", work)
    env = {k: v for k, v in installed.env.items() if not k.startswith("PYTEST_")}  # none of this run's options
    out = run([python, "-m", "pytest", "-v", "-p", "no:cacheprovider"], work, env, 300)
    print(f"\n--- the quick start's tests (pytest, cast.testing from the wheel):\n{out}")
    assert re.search(r"test_hello.py::test_hello_adds_three_greetings_and_stops_once_it_saw_them PASSED", out), out
    assert re.search(r"=+ 2 passed in ", out), out
    plugins = run([python, "-m", "pytest", "--version", "--version"], work, env)
    assert str(installed.venv) in plugins and "cast/testing/pytest_plugin.py" in plugins, plugins


# --------------------------------------------------------------------------------------------- C++

@pytest.fixture(scope="module")
def prefix(installed: Installed) -> Path:
    """The C++ library `make cpp` built, installed with `cmake --install` to a temporary prefix."""
    cmake = tool("cmake", "run `make cpp` (it installs the build tools)")
    if not (CPP_BUILD / "CMakeCache.txt").is_file():
        pytest.fail(f"{CPP_BUILD} is not a CMake build of cpp_client: run `make cpp` first")
    target = installed.work / "prefix"
    run([cmake, "--install", str(CPP_BUILD), "--prefix", str(target)], installed.work)
    return target


def test_the_installed_library_has_headers_package_and_pkg_config(prefix: Path) -> None:
    assert (prefix / "include" / "cast" / "cast.h").is_file()
    assert (prefix / "include" / "cast" / "testing.h").is_file()
    assert list((prefix / "lib").glob("libcast_testing.*"))
    assert (prefix / "include" / "cast" / "v1" / "directory.grpc.pb.h").is_file()
    # The headers are the tree's include/cast (the API, and detail/ that its templates need; docs/cpp.md,
    # "Headers"): nothing of cpp_client/src, such as the transport interface, is installed.
    headers = {str(p.relative_to(prefix / "include")) for p in (prefix / "include" / "cast").rglob("*.h")
               if p.parent.name != "v1"}
    tree = ROOT / "cpp_client" / "include"
    assert headers == {str(p.relative_to(tree)) for p in (tree / "cast").rglob("*.h")}, headers
    assert "cast/detail/records.h" in headers and "cast/transport.h" not in headers
    package = prefix / "lib" / "cmake" / "cast"
    assert {"castConfig.cmake", "castConfigVersion.cmake", "castTargets.cmake", "CastProtobuf.cmake"} <= {
        p.name for p in package.iterdir()}
    assert list((prefix / "lib").glob("libcast_client.*"))
    assert (prefix / "lib" / "pkgconfig" / "cast.pc").is_file()


def test_hello_builds_with_find_package_and_runs(installed: Installed, prefix: Path) -> None:
    cmake = tool("cmake", "run `make cpp` (it installs the build tools)")
    work = installed.work / "hello"
    shutil.copytree(ROOT / "examples" / "cpp" / "hello", work / "src")
    run([cmake, "-S", str(work / "src"), "-B", str(work / "build"), f"-DCMAKE_PREFIX_PATH={prefix}",
         "-DCMAKE_BUILD_TYPE=Release"], work)
    run([cmake, "--build", str(work / "build"), "-j2"], work, timeout=600)
    # Its test, with cast::testing finding the wheel's `cast` on PATH (installed.env: the venv first, no CAST_SERVE).
    tested = run(["ctest", "--test-dir", str(work / "build"), "--output-on-failure", "-V"], work, installed.env, 300)
    print(f"\n--- the C++ example's tests (ctest, GoogleTest, cast::testing from the prefix):\n{tested}")
    assert "[  PASSED  ] 2 tests." in tested and "100% tests passed" in tested, tested
    out = run([str(work / "build" / "hello_cpp")], work, installed.launch_env("hello-cpp", "greetings", {"count": 3}),
              60)
    assert [line.replace("hello-cpp:", "hello:") for line in hello_lines(out)] == HELLO_LINES, out
    row = installed.components()["hello-cpp"]
    assert (row["language"], row["library_version"]) == ("cpp", VERSION)


def test_find_package_refuses_another_minor_release(installed: Installed, prefix: Path) -> None:
    cmake = tool("cmake", "run `make cpp` (it installs the build tools)")
    project = installed.work / "wants-0.99"
    project.mkdir()
    (project / "CMakeLists.txt").write_text("cmake_minimum_required(VERSION 3.16)\nproject(wants LANGUAGES CXX)\n"
                                            "find_package(cast 0.99 CONFIG REQUIRED)\n")
    done = subprocess.run([cmake, "-S", str(project), "-B", str(project / "build"), f"-DCMAKE_PREFIX_PATH={prefix}"],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode != 0
    assert f"version: {VERSION}" in done.stdout + done.stderr, done.stdout + done.stderr


def test_pkg_config_links_a_program(installed: Installed, prefix: Path) -> None:
    pkg_config = tool("pkg-config", "run `make cpp` (it installs pkg-config)")
    compiler = tool("c++", "run `make cpp` (it installs g++)")
    env = {**os.environ, "PKG_CONFIG_PATH": str(prefix / "lib" / "pkgconfig")}
    assert run([pkg_config, "--modversion", "cast"], installed.work, env).strip() == VERSION
    flags = run([pkg_config, "--cflags", "--libs", "cast"], installed.work, env).split()
    source = installed.work / "versions.cc"
    source.write_text('#include <iostream>\n#include "cast/cast.h"\n'
                      'int main() { std::cout << cast::libraryVersion() << " " << cast::wireApi() << std::endl; }\n')
    run([compiler, "-std=c++17", str(source), *flags, "-o", str(installed.work / "versions")], installed.work,
        timeout=300)
    assert run([str(installed.work / "versions")], installed.work).strip() == f"{VERSION} cast.v1"


def test_the_library_builds_shared_with_build_shared_libs(installed: Installed) -> None:
    # Configured only (a shared build of the whole library takes minutes): the link step CMake
    # writes makes libcast_client.so with its soname.
    cmake = tool("cmake", "run `make cpp` (it installs the build tools)")
    build = installed.work / "shared"
    run([cmake, "-S", str(ROOT / "cpp_client"), "-B", str(build), "-DBUILD_SHARED_LIBS=ON",
         "-DCAST_BUILD_TESTS=OFF", "-DCAST_BUILD_EXAMPLES=OFF"], installed.work)
    link = (build / "CMakeFiles" / "cast_client.dir" / "link.txt").read_text()
    major, minor, _ = VERSION.split(".")
    assert "-shared" in link and f"-Wl,-soname,libcast_client.so.{major}.{minor}" in link, link


# -------------------------------------------------------------------------------------------- Java

def shared_sessions(endpoint: str, token: str) -> int:
    """How many shared-memory sessions the server at ``endpoint`` has open."""
    import grpc

    from cast.v1 import inspection_pb2, inspection_pb2_grpc

    with grpc.insecure_channel(endpoint) as channel:
        metrics = inspection_pb2_grpc.InspectionStub(channel).GetMetrics(
            inspection_pb2.GetMetricsRequest(), metadata=(("authorization", f"Bearer {token}"),), timeout=10)
    return int(metrics.shared_memory.sessions)


def test_the_java_example_builds_on_the_installed_artifacts_and_answers(installed: Installed) -> None:
    tool("mvn", "run `make java` (it installs a JDK and Maven)")
    java = tool("java", "run `make java` (it installs a JDK and Maven)")
    repository = maven_repository() / "cast"
    for artifact in ("cast-bom", "cast-client", "cast-testing"):
        if not (repository / artifact / VERSION).is_dir():
            pytest.fail(f"cast:{artifact}:{VERSION} is not installed in {repository.parent}: run `make java` first")
    work = installed.work / "java"
    shutil.copytree(ROOT / "examples" / "java", work, ignore=shutil.ignore_patterns("target"))
    # `mvn package` runs its JUnit test too, against the wheel's `cast` on PATH (installed.env).
    built = run([*maven(), "package"], work, installed.env, timeout=600)
    tested = "\n".join(line for line in built.splitlines()
                       if re.search(r"T E S T S|Running cast|Tests run:|MyComponentTest|BUILD", line))
    print(f"\n--- the Java example's tests (Maven, JUnit 5, cast-testing from the local repository):\n{tested}")
    assert "Tests run: 1, Failures: 0, Errors: 0, Skipped: 0" in built and "BUILD SUCCESS" in built, built[-6000:]
    classpath = (work / "target" / "classpath.txt").read_text().strip()
    jars = classpath.split(os.pathsep)
    assert jars[0] == str(repository / "cast-client" / VERSION / f"cast-client-{VERSION}.jar"), jars[0]
    assert not any(str(ROOT) in jar for jar in jars), "the example used a file of the tree"
    # junixsocket (shared memory on the server's host) comes along, its native library in its jar.
    assert {Path(jar).parent.parent.name for jar in jars} >= {"junixsocket-common", "junixsocket-native-common"}, jars

    gen = installed.work / "java-gen"
    gen.mkdir()
    run([sys.executable, "-m", "grpc_tools.protoc", f"-I{work / 'src' / 'main' / 'proto'}", f"--python_out={gen}",
         "greeting.proto"], installed.work)
    sys.path.insert(0, str(gen))
    try:
        from greeting_pb2 import Greeting  # type: ignore[import-not-found]
    finally:
        sys.path.remove(str(gen))

    import cast

    with installed.serve(work / "system.yaml") as endpoint:
        env = installed.launch_env("answerer", "greetings", {"prefix": "hello, "}, endpoint)
        component = subprocess.Popen([java, "-cp", f"{classpath}{os.pathsep}target/classes", "cast.client.Runner",
                                      "cast.examples.MyComponent"], cwd=work, env=env, stdout=subprocess.PIPE,
                                     stderr=subprocess.STDOUT, text=True)
        try:
            wait_for(lambda: installed.components(endpoint).get("answerer", {}).get("state") == "running", 60,
                     "the Java component running")
            row = installed.components(endpoint)["answerer"]
            assert (row["language"], row["library_version"]) == ("java", VERSION)
            token = installed.launch_env("greeter", "greetings", endpoint=endpoint)["CAST_TOKEN"]
            with cast.connect(endpoint=endpoint, token=token) as wm:
                answered = threading.Event()
                wm.on_change(cast.address_filter("reply-g1"), lambda change: answered.set())
                wm.add("g1", Greeting(text="world", **{"from": "greeter"}))
                assert answered.wait(60), "no answer from the Java component"
                assert wm.get("reply-g1", Greeting).text == "hello, world"
                # Both have a shared-memory session with the server: the Java one loaded junixsocket's
                # native library from the installed jar.
                assert shared_sessions(endpoint, token) == 2
        finally:
            component.send_signal(signal.SIGTERM)
            output = component.communicate(timeout=60)[0]
    assert component.returncode == 0, output
    assert "is not used" not in output, output  # no fallback to bytes: shared memory worked
