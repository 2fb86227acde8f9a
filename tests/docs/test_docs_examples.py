"""Every code block of docs/python.md, docs/cpp.md, docs/java.md and docs/design.md is tested.

How each block is tested is said by its marker (see tests/docs/pages.py): examples run against a
real server started on port 0 (C++ ones compiled against the library `make cpp` built, Java ones
against java_client/target/cast-client-all.jar) and print what the page shows; the pages' tests
of the testing kit pass under pytest, GoogleTest and JUnit, each starting its own systems; blocks
that show files are those files; the rest name the test that checks them, or are marked as
fragments.
"""

from __future__ import annotations

import ast
import json
import os
import py_compile
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import PYTHONPATH, SECRET, ServerHandle, maven, run_to_end
from tests.docs.pages import KINDS, MAX_FRAGMENTS, PAGES, ROOT, Block, blocks, normalise, shown

BIN = Path(sys.executable).parent
CPP_BUILD = ROOT / "build" / "cpp"
JAR = ROOT / "java_client" / "target" / "cast-client-all.jar"


def run_blocks() -> list[Block]:
    return [b for page in PAGES for b in blocks(page) if b.kind == "run"]


def output_after(block: Block) -> list[str] | None:
    """The normalised ``output`` block that follows a ``run`` block, if there is one."""
    page = blocks(block.page)
    after = page[page.index(block) + 1 :]
    if after and after[0].kind == "output":
        return normalise(after[0].code)
    return None


@pytest.mark.parametrize("page", PAGES)
def test_every_code_block_is_tested_or_marked_as_a_fragment(page: str) -> None:
    found = blocks(page)
    assert found, f"{page} has no code blocks"
    unmarked = [b.where for b in found if b.kind not in KINDS]
    assert not unmarked, f"code blocks without a marker saying how they are tested: {unmarked}"
    fragments = [b.where for b in found if b.kind == "fragment"]
    assert len(fragments) <= MAX_FRAGMENTS, f"too many fragments (keep them few): {fragments}"
    for i, b in enumerate(found):
        if b.kind == "output":
            assert i > 0 and found[i - 1].kind == "run", f"{b.where}: an output block must follow a run block"
        if b.kind in ("save", "file", "excerpt", "tested-by"):
            assert b.argument, f"{b.where}: '{b.kind}' needs an argument"


@pytest.mark.parametrize("page", PAGES)
def test_blocks_that_show_files_are_those_files(page: str) -> None:
    def squeeze(text: str) -> str:
        return re.sub(r"\s+", " ", text).strip()

    for b in blocks(page):
        if b.kind == "file":
            assert b.code == shown(b.argument), f"{b.where} is not {b.argument} as it is"
        elif b.kind == "excerpt":
            assert squeeze(b.code) in squeeze((ROOT / b.argument).read_text()), f"{b.where} is not in {b.argument}"


@pytest.mark.parametrize("page", PAGES)
def test_blocks_tested_elsewhere_name_a_test_that_reads_the_page(page: str) -> None:
    for b in blocks(page):
        if b.kind != "tested-by":
            continue
        path, _, name = b.argument.partition("::")
        source = (ROOT / path).read_text()
        names = {n.name for n in ast.walk(ast.parse(source)) if isinstance(n, ast.FunctionDef)}
        assert name in names, f"{b.where}: {path} has no test {name}"
        assert page in source, f"{b.where}: {path} does not read {page}"


@pytest.mark.parametrize("page", PAGES)
def test_saved_python_files_compile(page: str, tmp_path: Path) -> None:
    for b in blocks(page):
        if b.kind == "save" and b.argument.endswith(".py"):
            path = tmp_path / b.argument
            path.write_text(b.code)
            py_compile.compile(str(path), doraise=True)


def prepare(block: Block, work: Path) -> None:
    """The working directory of a run block: the page's saved files so far, and the built trees."""
    for b in blocks(block.page):
        if b is block or b.line > block.line:
            break
        if b.kind == "save":
            (work / b.argument).write_text(b.code)
    # Commands on the C++ and Java pages name paths from the repository root.
    for name in ("cpp_client", "build", "java_client"):
        (work / name).symlink_to(ROOT / name)


def clean_env() -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("CAST_")}
    env["PATH"] = f"{BIN}{os.pathsep}{env.get('PATH', '')}"
    return env


def check(proc: subprocess.CompletedProcess[str], block: Block) -> None:
    assert proc.returncode == 0, f"{block.where} exited {proc.returncode}\n{proc.stdout}\n{proc.stderr}"
    expected = output_after(block)
    if expected is not None:
        assert normalise(proc.stdout) == expected, f"{block.where} printed:\n{proc.stdout}\n{proc.stderr}"


def need_cpp() -> None:
    for lib in ("libcast_client.a", "libcast_v1_proto.a"):
        if not (CPP_BUILD / lib).is_file():
            pytest.fail(f"{CPP_BUILD / lib} is missing: run `make cpp` first")


def need_java() -> None:
    if not JAR.is_file():
        pytest.fail(f"{JAR} is missing: run `make java` first")
    if shutil.which("javac") is None:
        pytest.fail("javac is not installed: run `make java` (it installs a JDK)")


def compile_cpp(source: Path) -> Path:
    """Compile and link a C++ example against the library `make cpp` built."""
    need_cpp()
    libs = subprocess.run(["pkg-config", "--libs", "grpc++", "protobuf", "libcrypto"], capture_output=True,
                          text=True, check=True).stdout.split()
    binary = source.with_suffix("")
    made = subprocess.run(
        ["c++", "-std=c++17", f"-I{ROOT / 'cpp_client' / 'include'}", str(source),
         str(CPP_BUILD / "libcast_client.a"), str(CPP_BUILD / "libcast_v1_proto.a"), *libs, "-o", str(binary)],
        capture_output=True, text=True, timeout=300,
    )
    assert made.returncode == 0, f"{source.name} does not compile:\n{made.stderr[-6000:]}"
    return binary


def java_command(block: Block, work: Path) -> list[str]:
    """Compile a Java example; the command that runs it (the runner for a component, else its main)."""
    need_java()
    name = re.search(r"public (?:final )?class (\w+)", block.code)
    assert name, f"{block.where}: no public class"
    source = work / f"{name[1]}.java"
    source.write_text(block.code)
    classes = work / "classes"
    made = subprocess.run(["javac", "-cp", str(JAR), "-d", str(classes), str(source)], capture_output=True,
                          text=True, timeout=300)
    assert made.returncode == 0, f"{source.name} does not compile:\n{made.stderr[-6000:]}"
    classpath = f"{JAR}{os.pathsep}{classes}"
    if re.search(r"extends (Unmanaged|Managed)Component\b", block.code):
        return ["java", "-cp", classpath, "cast.client.Runner", name[1]]
    return ["java", "-cp", classpath, name[1]]


EXAMPLE_TIMEOUT_S = 90
"""Under pytest-timeout's 120 s, so that a hung example is reported with what it printed and its stacks."""


def run_example(command: list[str], cwd: Path, env: dict[str, str], block: Block) -> subprocess.CompletedProcess[str]:
    """Run an example; one that hangs fails with its output and its threads' stacks (tests/conftest.py)."""
    return run_to_end(command, block.where, EXAMPLE_TIMEOUT_S, cwd=cwd, env=env)


@pytest.mark.parametrize("block", run_blocks(), ids=lambda b: b.where)
def test_the_example_runs_and_prints_what_the_page_shows(block: Block, server: ServerHandle, tmp_path: Path) -> None:
    work = tmp_path / "work"
    work.mkdir()
    prepare(block, work)
    if block.lang == "sh":
        env = clean_env()
        env.update(CAST_ENDPOINT=server.endpoint, CAST_SECRET=SECRET)
        check(run_example(["bash", "-e", "-c", block.code], work, env, block), block)
        return
    args = json.loads(block.attrs.get("args", "{}"))
    env = clean_env()
    env.update(server.env(block.attrs.get("as", "notebook"), block.attrs.get("sa", "vision"), args=args))
    env["PATH"] = clean_env()["PATH"]
    if block.lang == "python":
        env["PYTHONPATH"] = f"{work}{os.pathsep}{PYTHONPATH}"
        main = block.attrs.get("main")
        if main:
            (work / f"{main.split(':')[0]}.py").write_text(block.code)
            command = [sys.executable, "-m", "cast.run", main]
        else:
            (work / "example.py").write_text(block.code)
            command = [sys.executable, "example.py"]
    elif block.lang == "cpp":
        source = work / f"{block.attrs.get('as', 'example')}.cc"
        source.write_text(block.code)
        command = [str(compile_cpp(source))]
    elif block.lang == "java":
        command = java_command(block, work)
    else:
        raise AssertionError(f"{block.where}: no way to run a '{block.lang}' block")
    check(run_example(command, work, env, block), block)


# ------------------------------------------------------------------ the pages' tests of the testing kit


def kit_test_blocks() -> list[Block]:
    return [b for page in PAGES for b in blocks(page) if b.kind == "test"]


JAVA_TEST_POM = """<?xml version="1.0" encoding="UTF-8"?>
<project xmlns="http://maven.apache.org/POM/4.0.0">
  <modelVersion>4.0.0</modelVersion>
  <groupId>docs</groupId>
  <artifactId>page-test</artifactId>
  <version>1</version>
  <properties>
    <maven.compiler.release>17</maven.compiler.release>
    <project.build.sourceEncoding>UTF-8</project.build.sourceEncoding>
  </properties>
  <dependencyManagement>
    <dependencies>
      <dependency>
        <groupId>cast</groupId><artifactId>cast-bom</artifactId><version>{version}</version>
        <type>pom</type><scope>import</scope>
      </dependency>
    </dependencies>
  </dependencyManagement>
  <dependencies>
    <dependency><groupId>cast</groupId><artifactId>cast-client</artifactId></dependency>
    <dependency><groupId>cast</groupId><artifactId>cast-testing</artifactId><scope>test</scope></dependency>
    <dependency>
      <groupId>org.junit.jupiter</groupId><artifactId>junit-jupiter</artifactId><version>5.10.2</version>
      <scope>test</scope>
    </dependency>
  </dependencies>
  <build>
    <plugins>
      <plugin>
        <groupId>org.apache.maven.plugins</groupId><artifactId>maven-compiler-plugin</artifactId><version>3.13.0</version>
      </plugin>
      <plugin>
        <groupId>org.apache.maven.plugins</groupId><artifactId>maven-resources-plugin</artifactId><version>3.3.1</version>
      </plugin>
      <plugin>
        <groupId>org.apache.maven.plugins</groupId><artifactId>maven-surefire-plugin</artifactId><version>3.2.5</version>
      </plugin>
    </plugins>
  </build>
</project>
"""


@pytest.mark.timeout(600)  # a compile or a Maven build on a busy 2-core machine, then the tests' own servers
@pytest.mark.parametrize("block", kit_test_blocks(), ids=lambda b: b.where)
def test_the_pages_tests_pass_with_the_testing_kit(block: Block, tmp_path: Path) -> None:
    work = tmp_path / "work"
    work.mkdir()
    prepare(block, work)
    env = clean_env()  # `cast` on PATH: the kits find the server there, as in a user's activated environment
    if block.lang == "python":
        (work / "test_page.py").write_text(block.code)
        env = {k: v for k, v in env.items() if not k.startswith(("PYTEST_", "PYTHONPATH"))}
        command = [sys.executable, "-m", "pytest", "-v", "-p", "no:cacheprovider", "test_page.py"]
        passed = r"=+ (\d+) passed in "
    elif block.lang == "cpp":
        need_cpp()
        source = work / "page_test.cc"
        source.write_text(block.code)
        libs = subprocess.run(["pkg-config", "--libs", "grpc++", "protobuf", "libcrypto", "gtest_main"],
                              capture_output=True, text=True, check=True).stdout.split()
        binary = work / "page_test"
        made = subprocess.run(
            ["c++", "-std=c++17", f"-I{ROOT / 'cpp_client' / 'include'}", str(source),
             str(CPP_BUILD / "libcast_testing.a"), str(CPP_BUILD / "libcast_client.a"),
             str(CPP_BUILD / "libcast_v1_proto.a"), *libs, "-o", str(binary)],
            capture_output=True, text=True, timeout=300,
        )
        assert made.returncode == 0, f"{block.where} does not compile:\n{made.stderr[-6000:]}"
        command = [str(binary)]
        passed = r"\[  PASSED  \] (\d+) tests?\."
    elif block.lang == "java":
        need_java()
        name = re.search(r"^class (\w+)", block.code, re.M)
        assert name, f"{block.where}: no test class"
        (work / "src" / "test" / "java").mkdir(parents=True)
        (work / "src" / "test" / "java" / f"{name[1]}.java").write_text(block.code)
        (work / "pom.xml").write_text(JAVA_TEST_POM.format(version=(ROOT / "VERSION").read_text().strip()))
        command = [*maven(), "test"]
        passed = r"Tests run: (\d+), Failures: 0, Errors: 0, Skipped: 0\n"
    else:
        raise AssertionError(f"{block.where}: no test framework for a '{block.lang}' block")
    done = run_to_end(command, block.where, 480, cwd=work, env=env)
    printed = done.stdout + done.stderr
    assert done.returncode == 0, f"{block.where}'s tests failed ({done.returncode}):\n{printed[-8000:]}"
    counted = re.search(passed, printed)
    assert counted and int(counted[1]) >= 2, f"{block.where}: fewer tests passed than the page has:\n{printed[-4000:]}"
