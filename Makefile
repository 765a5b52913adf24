# dmdsm: `make demo` runs the main job on the emulator; `make test` runs every test.
# Both install what is missing first (apt packages once, then a local .venv).

SHELL := /bin/bash
.SHELLFLAGS := -eo pipefail -c
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
PY := $(VENV)/bin/python
STAMPS := build/stamps
HOSTBUILD := build/host
AVRBUILD := build/avr
FUZZ_SECONDS ?= 20

APT_PACKAGES := gcc make clang libclang-rt-14-dev cppcheck gcc-arm-none-eabi \
  libnewlib-arm-none-eabi qemu-system-arm simavr libsimavr-dev libelf-dev pkg-config \
  gcc-avr avr-libc chromium chromium-driver
CFLAGS_HOST := -std=c11 -Wall -Wextra -Werror -pedantic -g -O1
SANITIZE := -fsanitize=address,undefined -fno-sanitize-recover=all -fno-omit-frame-pointer
PROTO_C := protocol/c/dmdsm_frame.c protocol/c/dmdsm_spec.c
PROTO_H := protocol/c/dmdsm_frame.h protocol/c/dmdsm_spec.h
CORE_C := $(wildcard firmware/stm32/core/*.c)
CORE_H := $(wildcard firmware/stm32/core/*.h)

.PHONY: all deps venv build firmware avr test test-fast index test-c fuzz lint gen-check gen bench demo clean \
  check-marlin

all: build

## ---------------------------------------------------------------- install
# apt-get update runs once, and only if a package is missing (checked again when this
# Makefile changes, so a package added here is installed on an existing checkout too).
$(STAMPS)/apt: Makefile
	@mkdir -p $(STAMPS)
	@missing=""; for p in $(APT_PACKAGES); do \
	  dpkg-query -W -f='$${Status}' $$p 2>/dev/null | grep -q "ok installed" || missing="$$missing $$p"; \
	done; \
	if ! $(PYTHON) -c 'import ensurepip, venv' 2>/dev/null; then missing="$$missing python3-venv"; fi; \
	if ! $(PYTHON) -c 'import os, sysconfig; assert os.path.exists(os.path.join(sysconfig.get_paths()["include"], "Python.h"))' 2>/dev/null; \
	  then missing="$$missing python3-dev"; fi; \
	if [ -n "$$missing" ]; then \
	  echo "installing:$$missing"; \
	  export DEBIAN_FRONTEND=noninteractive; \
	  apt-get update -qq && apt-get install -y -qq --no-install-recommends $$missing; \
	fi
	@touch $@

$(VENV)/stamp: pyproject.toml | $(STAMPS)/apt
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[dev]'
	@$(PY) -c 'from dmdsm.protocol import cobs_extension_loaded as c; assert c(), "cobs C extension did not build"'
	@touch $@

deps: $(STAMPS)/apt $(VENV)/stamp
venv: $(VENV)/stamp

## ---------------------------------------------------------------- build
$(HOSTBUILD)/test_frame: $(PROTO_C) $(PROTO_H) tests/c/test_frame.c tests/c/vectors.c tests/c/vectors.h tests/c/check.h | $(STAMPS)/apt
	@mkdir -p $(HOSTBUILD)
	gcc $(CFLAGS_HOST) $(SANITIZE) -Iprotocol/c -Itests/c $(PROTO_C) tests/c/test_frame.c tests/c/vectors.c -o $@

$(HOSTBUILD)/test_core: $(PROTO_C) $(PROTO_H) $(CORE_C) $(CORE_H) tests/c/test_core.c tests/c/check.h | $(STAMPS)/apt
	@mkdir -p $(HOSTBUILD)
	gcc $(CFLAGS_HOST) $(SANITIZE) -Iprotocol/c -Ifirmware/stm32/core -Itests/c $(PROTO_C) $(CORE_C) tests/c/test_core.c -o $@

$(HOSTBUILD)/proto_tool: $(PROTO_C) $(PROTO_H) tests/c/proto_tool.c | $(STAMPS)/apt
	@mkdir -p $(HOSTBUILD)
	gcc $(CFLAGS_HOST) $(SANITIZE) -Iprotocol/c $(PROTO_C) tests/c/proto_tool.c -o $@

$(HOSTBUILD)/fuzz_decoder: $(PROTO_C) $(PROTO_H) tests/c/fuzz_decoder.c | $(STAMPS)/apt
	@mkdir -p $(HOSTBUILD)
	clang -std=c11 -Wall -Wextra -Werror -g -O1 -fsanitize=fuzzer,address,undefined \
	  -Iprotocol/c $(PROTO_C) tests/c/fuzz_decoder.c -o $@

# every firmware build: the NUCLEO, QEMU's Cortex-M7 and the PC library for the SIL
firmware: $(STAMPS)/apt
	$(MAKE) -C firmware/stm32 BOARD=nucleo_h743zi
	$(MAKE) -C firmware/stm32 BOARD=qemu_an500
	$(MAKE) -C firmware/stm32 BOARD=pc

# the stage board's firmware under simavr (docs/marlin.md), and an AVR program to test it with
HARNESS_C := hil_sim/avr/stage_harness.c hil_sim/avr/harness_pty.c hil_sim/avr/harness_lockstep.c
$(AVRBUILD)/stage_harness: $(HARNESS_C) hil_sim/avr/harness.h | $(STAMPS)/apt
	@mkdir -p $(AVRBUILD)
	gcc -std=gnu11 -Wall -Wextra -Werror -O2 $(HARNESS_C) $$(pkg-config --cflags --libs simavr) -lutil -o $@

$(AVRBUILD)/uart_pins_test.elf: hil_sim/avr/uart_pins_test.c | $(STAMPS)/apt
	@mkdir -p $(AVRBUILD)
	avr-gcc -mmcu=atmega2560 -std=gnu11 -Os -DF_CPU=16000000UL -Wall -Wextra -Werror $< -o $@

avr: $(AVRBUILD)/stage_harness $(AVRBUILD)/uart_pins_test.elf

build: deps firmware avr $(HOSTBUILD)/test_frame $(HOSTBUILD)/test_core $(HOSTBUILD)/proto_tool $(HOSTBUILD)/fuzz_decoder

## ---------------------------------------------------------------- checks
gen: deps
	$(PY) -m dmdsm.protocol.gen_c
	$(PY) -m dmdsm.protocol.gen_docs

gen-check: deps
	$(PY) -m dmdsm.protocol.gen_c --check
	$(PY) -m dmdsm.protocol.gen_docs --check

# import-linter reads the packages from disk: build/importgraph/dmdsm is the installed
# package's layout (dmdsm.host = host/, dmdsm.sim = hil_sim/, ...) as symbolic links.
IMPORTGRAPH := build/importgraph
lint: deps
	$(PY) -m ruff check protocol host hil_sim tests bench firmware/marlin_patch
	@rm -rf $(IMPORTGRAPH) && mkdir -p $(IMPORTGRAPH)/dmdsm
	@ln -s $(CURDIR)/host $(IMPORTGRAPH)/dmdsm/host
	@ln -s $(CURDIR)/hil_sim $(IMPORTGRAPH)/dmdsm/sim
	@ln -s $(CURDIR)/protocol $(IMPORTGRAPH)/dmdsm/protocol
	@ln -s $(CURDIR)/firmware/marlin_patch $(IMPORTGRAPH)/dmdsm/marlin_patch
	@echo '"""dmdsm, laid out for lint-imports."""' > $(IMPORTGRAPH)/dmdsm/__init__.py
	cd $(IMPORTGRAPH) && PYTHONPATH=. $(CURDIR)/$(VENV)/bin/lint-imports --no-cache \
	  $(CURDIR)/pyproject.toml
	cppcheck --quiet --error-exitcode=1 --enable=warning,style,performance,portability \
	  --std=c11 --inline-suppr -Iprotocol/c -Ifirmware/stm32/core protocol/c firmware/stm32/core tests/c
	cppcheck --quiet --error-exitcode=1 --enable=warning,style,performance,portability \
	  --std=c11 --inline-suppr --suppress=missingIncludeSystem -Iprotocol/c -Ifirmware/stm32/core \
	  -Ifirmware/stm32/board/common -Ifirmware/stm32/board/nucleo_h743zi firmware/stm32/board
	cppcheck --quiet --error-exitcode=1 --enable=warning,style,performance,portability \
	  --std=c11 --suppress=missingIncludeSystem -Ihil_sim/avr $(HARNESS_C)

test-c: build
	ASAN_OPTIONS=detect_leaks=1 $(HOSTBUILD)/test_frame protocol/vectors/golden.txt
	ASAN_OPTIONS=detect_leaks=1 $(HOSTBUILD)/test_core

fuzz: build
	@mkdir -p build/fuzz_corpus
	$(PY) -c 'import json,pathlib; [pathlib.Path("build/fuzz_corpus/%s" % r["name"]).write_bytes(bytes.fromhex(r["frame"])) for r in json.load(open("protocol/vectors/golden.json"))]'
	$(HOSTBUILD)/fuzz_decoder -max_total_time=$(FUZZ_SECONDS) -max_len=4096 -print_final_stats=1 \
	  build/fuzz_corpus 2>&1 | tail -n 4

# aeon's numba kernels (BOSS, MiniRocket) compile once, beside the builds and lint, into
# numba's on-disk cache: cold they take ~3 min of CPU, and each test worker and the demo
# would otherwise compile them again at the same time (dmdsm.host.classify.warm).
QUIET_TESTS := tests/test_live.py tests/test_live_server.py

test: deps
	@mkdir -p build; $(PY) -m dmdsm.host.classify.warm > build/warm.log 2>&1 & warm=$$!; \
	$(MAKE) --no-print-directory build gen-check lint test-c fuzz || { kill $$warm; exit 1; }; \
	wait $$warm || { cat build/warm.log; echo "aeon warm-up failed" >&2; exit 1; }; \
	cat build/warm.log
	@# the full demo (mostly waiting on the real-time emulator) runs beside the other tests;
	@# QUIET_TESTS run after it, alone: their truth is the emulator's wall-clock pacing
	@# (live stamps)
	@rc=0; drc=0; qrc=0; \
	DMDSM_PROTO_TOOL=$(HOSTBUILD)/proto_tool $(PY) -m pytest -q -p no:cacheprovider tests/demo \
	  > build/test-demo.log 2>&1 & demo=$$!; \
	DMDSM_PROTO_TOOL=$(HOSTBUILD)/proto_tool $(PY) -m pytest -q -n 4 --dist loadfile \
	  --durations=15 --ignore=tests/demo $(addprefix --ignore=,$(QUIET_TESTS)) || rc=$$?; \
	wait $$demo || drc=$$?; \
	echo "---- tests/demo (the full demo, run beside the others)"; cat build/test-demo.log; \
	echo "---- $(QUIET_TESTS) (alone)"; \
	DMDSM_PROTO_TOOL=$(HOSTBUILD)/proto_tool $(PY) -m pytest -q -p no:cacheprovider \
	  $(QUIET_TESTS) || qrc=$$?; \
	exit $$(( rc || drc || qrc ))

# the inner loop: every test that does not serve a board in real time (`-m "not realtime"`)
test-fast: deps build
	DMDSM_PROTO_TOOL=$(HOSTBUILD)/proto_tool $(PY) -m pytest -q -n 2 -m "not realtime" \
	  --ignore=tests/demo

index: deps
	$(PY) tests/index.py

bench: deps firmware
	$(PY) bench/protocol.py
	$(PY) bench/firmware.py
	$(PY) bench/links.py
	$(PY) bench/ranging.py
	$(PY) bench/calibration.py
	$(PY) bench/emulator.py
	$(PY) bench/scan.py
	$(PY) bench/sensor_limits.py
	$(PY) bench/scan_coverage.py --quick
	$(PY) bench/model.py --quick --band-mm 8
	$(PY) bench/classify.py
	$(PY) bench/live.py --quick

## ---------------------------------------------------------------- the real Marlin
# make check-marlin MARLIN=DIR: patch and build that Marlin checkout (with the Chiron example
# configuration copied in: docs/marlin.md), run the stage conformance, fault and scan suites
# against the built firmware under simavr, then random G-code to it and to the emulator. Marlin's code stays in DIR; the build goes to
# build/marlin. APPLY_FLAGS=--force patches a Marlin version other than the pinned one.
MARLIN_BUILD := build/marlin
check-marlin: deps avr
	@test -n "$(MARLIN)" || { echo "usage: make check-marlin MARLIN=/path/to/Marlin (docs/marlin.md)" >&2; exit 2; }
	@dpkg-query -W -f='$${Status}' arduino-core-avr 2>/dev/null | grep -q "ok installed" || { \
	  echo "installing: arduino-core-avr"; export DEBIAN_FRONTEND=noninteractive; \
	  apt-get update -qq && apt-get install -y -qq --no-install-recommends arduino-core-avr; }
	$(PY) firmware/marlin_patch/apply.py $(APPLY_FLAGS) $(MARLIN)
	sh firmware/marlin_patch/build_debian.sh $(MARLIN) $(CURDIR)/$(MARLIN_BUILD)
	@# every step runs whatever an earlier one found, and the end reports each
	@rc=0; drc=0; \
	DMDSM_STAGE_FIRMWARE=$(CURDIR)/$(MARLIN_BUILD)/Marlin.elf $(PY) -m pytest -q -p no:cacheprovider \
	  -rfE --durations=10 tests/stage || rc=$$?; \
	$(PY) tests/stage/differential.py $(MARLIN_BUILD)/Marlin.elf --lines 150 || drc=$$?; \
	echo "---- check-marlin: tests/stage $$( [ $$rc = 0 ] && echo passed || echo "FAILED ($$rc)"), differential $$( [ $$drc = 0 ] && echo passed || echo "FAILED ($$drc)")"; \
	exit $$(( rc || drc ))

## ---------------------------------------------------------------- demo
demo: deps
	$(VENV)/bin/dmdsm demo --out out

clean:
	rm -rf build out
	$(MAKE) -C firmware/stm32 clean
