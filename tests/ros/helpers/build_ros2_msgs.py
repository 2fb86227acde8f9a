"""Build a ROS 2 message package from its .msg files with the rosidl generators of the ROS 2 wheels and gcc.

    build_ros2_msgs.py PACKAGE_DIR PREFIX

PACKAGE_DIR holds ``msg/*.msg`` (the package's name is the directory's);
PREFIX becomes its install space, laid out as colcon installs one:
``lib/lib<pkg>__<typesupport>.so``, ``lib/python3.X/site-packages/<pkg>``,
``include/<pkg>``, ``share/<pkg>/msg`` (.msg, .idl, .json) and the ament
index. What a sourced ``setup.bash`` would set for it is printed as JSON on
the last line (PYTHONPATH, LD_LIBRARY_PATH, AMENT_PREFIX_PATH).

It runs with the ROS 2 interpreter (``.venv-ros2``) and does what
``rosidl_generate_interfaces`` does in CMake, without colcon or ament_cmake,
which the wheels do not have: rosidl_adapter (.msg -> .idl),
rosidl_generator_type_description (the type hashes), rosidl_generator_c,
rosidl_typesupport_introspection_c, rosidl_typesupport_fastrtps_c (what
rmw_fastrtps_cpp serialises with), rosidl_typesupport_c (the dispatch rclpy
loads) and rosidl_generator_py, then gcc and g++ against the headers and
libraries of the wheels (which have no RPATHs: the libraries are found on
LD_LIBRARY_PATH, as in a sourced ROS installation). The rosidl command line
cannot drive it here: the wheels register each generator twice (an egg-info
and a dist-info), and rosidl_cli refuses duplicate extensions; so the
generators' own extension classes are called.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import sysconfig
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

ROS = Path(sys.prefix)  # the wheels install their headers, libraries and share/ into the venv
SITE = f"lib/python{sys.version_info.major}.{sys.version_info.minor}/site-packages"
CFLAGS = ["-fPIC", "-O1", "-w"]  # generated code; -w: its warnings are rosidl's, not ours to read


def dependencies(msg_files: list[Path], package: str) -> list[str]:
    """The message packages the .msg files nest types from (builtin_interfaces for time and duration)."""
    from rosidl_adapter.parser import parse_message_string

    found: set[str] = set()
    for path in msg_files:
        for field in parse_message_string(package, path.stem, path.read_text(encoding="utf-8")).fields:
            if not field.type.is_primitive_type() and field.type.pkg_name:
                found.add(field.type.pkg_name)
            elif field.type.type in ("time", "duration"):
                found.add("builtin_interfaces")
    found.discard(package)
    missing = [p for p in sorted(found) if not (ROS / "share" / p / "msg").is_dir()]
    if missing:
        sys.exit(f"build_ros2_msgs: {package} uses messages of {', '.join(missing)}, which this ROS 2 "
                 f"({ROS}) does not have")
    return sorted(found)


def generate(package: str, source: Path, work: Path, share: Path) -> dict[str, list[Path]]:
    """Run the generators; the generated files by generator (idl, c, introspection_c, fastrtps_c, typesupport_c, py)."""
    from rosidl_adapter.msg import convert_msg_to_idl
    from rosidl_cli.command.hash.api import generate_type_hashes
    from rosidl_generator_c.cli import GenerateC
    from rosidl_generator_py.cli import GeneratePython
    from rosidl_typesupport_c.cli import GenerateCTypesupport
    from rosidl_typesupport_fastrtps_c.cli import GenerateFastRTPSCTypesupport
    from rosidl_typesupport_introspection_c.cli import GenerateIntrospectionCTypesupport

    msgs = sorted((source / "msg").glob("*.msg"))
    (share / "msg").mkdir(parents=True, exist_ok=True)
    idl = []
    for msg in msgs:
        shutil.copy(msg, share / "msg" / msg.name)
        convert_msg_to_idl(source.resolve(), package, Path("msg") / msg.name, share / "msg")
        idl.append(f"{share}:msg/{msg.stem}.idl")
    includes = [str(ROS / "share")]
    descriptions = generate_type_hashes(package_name=package, interface_files=idl, include_paths=includes,
                                        output_path=share)
    out: dict[str, list[Path]] = {}
    # Headers go under <dir>/<package>/ as CMake lays them out: sources include "<package>/msg/...".
    for name, extension, kwargs in (
        ("c", GenerateC("c"), {"type_description_files": descriptions}),
        ("introspection_c", GenerateIntrospectionCTypesupport("introspection_c"), {}),
        ("fastrtps_c", GenerateFastRTPSCTypesupport("fastrtps_c"), {}),
        ("typesupport_c", GenerateCTypesupport("c"), {}),
        ("py", GeneratePython("py"), {}),
    ):
        files = extension.generate(package, idl, includes, output_path=work / name / package, **kwargs)
        out[name] = [Path(f) for f in files]
    return out


def compile_all(jobs: list[tuple[Path, Path]], includes: list[Path]) -> None:
    """Compile each (source, object) pair, two at a time (the machines this runs on have two cores)."""
    flags = [*CFLAGS, *(f"-I{i}" for i in includes)]

    def one(job: tuple[Path, Path]) -> str:
        source, obj = job
        compiler = "g++" if source.suffix == ".cpp" else "gcc"
        done = subprocess.run([compiler, *flags, "-c", str(source), "-o", str(obj)], capture_output=True, text=True)
        return f"{compiler} {source}:\n{done.stderr}" if done.returncode else ""

    with ThreadPoolExecutor(2) as pool:
        errors = [e for e in pool.map(one, jobs) if e]
    if errors:
        sys.exit("build_ros2_msgs: compiling failed\n" + "\n".join(errors))


def link(output: Path, objects: list[Path], libs: list[str], lib_dirs: list[Path], cxx: bool = False) -> None:
    """Link a shared library (no RPATH: the wheels' own libraries have none either)."""
    command = ["g++" if cxx else "gcc", "-shared", "-o", str(output), *map(str, objects),
               *(f"-L{d}" for d in lib_dirs), *(f"-Wl,-rpath-link,{d}" for d in lib_dirs),
               f"-Wl,-soname,{output.name}", *(f"-l{lib}" for lib in libs)]
    done = subprocess.run(command, capture_output=True, text=True)
    if done.returncode:
        sys.exit(f"build_ros2_msgs: linking {output.name} failed:\n{' '.join(command)}\n{done.stderr}")


def check_tools() -> None:
    """Stop, naming what to install, when a compiler or the Python headers are missing."""
    missing = [tool for tool in ("gcc", "g++") if shutil.which(tool) is None]
    if missing:
        sys.exit(f"build_ros2_msgs: {' and '.join(missing)} not found: `make cpp` installs them (Debian's g++)")
    headers = Path(sysconfig.get_paths()["include"]) / "Python.h"
    if not headers.is_file():
        sys.exit(f"build_ros2_msgs: no {headers}: the Python of {sys.prefix} has no C headers (Debian: python3-dev)")


def build(source: Path, prefix: Path) -> dict[str, str]:
    """Build the package in ``source`` into the install space ``prefix``; the environment that puts it on the path."""
    check_tools()
    package = source.name
    msgs = sorted((source / "msg").glob("*.msg"))
    if not msgs:
        sys.exit(f"build_ros2_msgs: no .msg files in {source / 'msg'}")
    deps = dependencies(msgs, package)
    work = prefix / "build"
    share = prefix / "share" / package
    generated = generate(package, source, work, share)

    # The generated sources and their objects; headers stay where they were generated (and are installed).
    include_roots = [work / kind for kind in ("c", "introspection_c", "fastrtps_c")]
    # ROS packages install headers under include/<pkg>/<pkg>/, vendored ones (fastcdr) under include/<name>/.
    includes = [*include_roots, *sorted(d for d in (ROS / "include").iterdir() if d.is_dir()), ROS / "include",
                Path(sysconfig.get_paths()["include"]), Path(__import__("numpy").get_include())]
    objects: dict[str, list[Path]] = {}
    jobs = []
    for kind, files in generated.items():
        if kind == "py":
            # The message classes' C half, and the one typesupport entry point rclpy imports
            # (rosidl_generator_py.import_type_support: <pkg>_s__rosidl_typesupport_c).
            files = [f for f in files if f.name.endswith("_s.c") or f.name.endswith(".ep.rosidl_typesupport_c.c")]
        for f in files:
            if f.suffix in (".c", ".cpp"):
                obj = work / "obj" / kind / f"{f.name}.o"
                obj.parent.mkdir(parents=True, exist_ok=True)
                jobs.append((f, obj))
                objects.setdefault(kind, []).append(obj)
    compile_all(jobs, includes)

    lib = prefix / "lib"
    lib.mkdir(parents=True, exist_ok=True)
    dirs = [lib, ROS / "lib"]
    gen_c = f"{package}__rosidl_generator_c"
    link(lib / f"lib{gen_c}.so", objects["c"], [*(f"{d}__rosidl_generator_c" for d in deps), "rosidl_runtime_c",
                                                  "rcutils"], dirs)
    link(lib / f"lib{package}__rosidl_typesupport_introspection_c.so", objects["introspection_c"],
         [gen_c, *(f"{d}__rosidl_typesupport_introspection_c" for d in deps), "rosidl_typesupport_introspection_c",
          "rosidl_runtime_c", "rcutils"], dirs)
    link(lib / f"lib{package}__rosidl_typesupport_fastrtps_c.so", objects["fastrtps_c"],
         [gen_c, *(f"{d}__rosidl_typesupport_fastrtps_c" for d in deps), *(f"{d}__rosidl_generator_c" for d in deps),
          "rosidl_typesupport_fastrtps_c", "rosidl_typesupport_fastrtps_cpp", "rosidl_dynamic_typesupport", "rmw",
          "fastcdr", "rosidl_runtime_c", "rcutils"], dirs, cxx=True)
    link(lib / f"lib{package}__rosidl_typesupport_c.so", objects["typesupport_c"],
         [gen_c, "rosidl_typesupport_c", "rosidl_runtime_c", "rcutils"], dirs, cxx=True)
    gen_py = f"{package}__rosidl_generator_py"
    link(lib / f"lib{gen_py}.so", [o for o in objects["py"] if o.name.endswith("_s.c.o")],
         [gen_c, f"{package}__rosidl_typesupport_c", *(f"{d}__rosidl_generator_py" for d in deps),
          *(f"{d}__rosidl_generator_c" for d in deps), "rosidl_runtime_c", "rcutils"], dirs)

    # The Python package: the generated modules, and the entry point as an extension module beside them.
    site = prefix / SITE / package
    shutil.copytree(work / "py" / package, site, ignore=shutil.ignore_patterns("*.c"), dirs_exist_ok=True)
    (site / "__init__.py").touch()
    link(site / f"{package}_s__rosidl_typesupport_c.so", [o for o in objects["py"] if ".ep." in o.name],
         [gen_py, f"{package}__rosidl_typesupport_c", gen_c, "rosidl_runtime_c", "rcutils"], dirs)

    # Headers, and the ament index entries a ROS installation has for an interface package.
    for root in include_roots:
        shutil.copytree(root / package, prefix / "include" / package / package, dirs_exist_ok=True,
                        ignore=shutil.ignore_patterns("*.c", "*.cpp"))
    index = prefix / "share" / "ament_index" / "resource_index"
    (index / "packages").mkdir(parents=True, exist_ok=True)
    (index / "packages" / package).write_text("")
    (index / "rosidl_interfaces").mkdir(parents=True, exist_ok=True)
    (index / "rosidl_interfaces" / package).write_text(
        "\n".join(f"msg/{m.stem}.{ext}" for m in msgs for ext in ("idl", "msg")))
    shutil.rmtree(work)
    return {"PYTHONPATH": str(prefix / SITE), "LD_LIBRARY_PATH": str(lib), "AMENT_PREFIX_PATH": str(prefix)}


def main() -> int:
    """Build ``argv[1]`` into ``argv[2]``; print the environment that puts it on the ROS path."""
    source, prefix = Path(sys.argv[1]).resolve(), Path(sys.argv[2]).resolve()
    os.environ.setdefault("AMENT_PREFIX_PATH", str(ROS))  # the generators find their templates through it
    print(json.dumps(build(source, prefix)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
