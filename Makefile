# capsheet — the two commands: `make demo` and `make test`. Each builds .venv itself.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed-stamp

.PHONY: demo test bench clean

# uv resolves and installs in parallel (a fresh set-up in under a minute where pip took two); pinned
# so every machine installs with the same resolver. It goes into the venv, nothing outside it.
UV_VERSION := 0.13.9
UV         := $(VENV)/bin/uv

$(STAMP): pyproject.toml $(wildcard setup.py) $(wildcard firmware_ref/*.c firmware_ref/*.h firmware_ref/*/*.c firmware_ref/*/*.h) $(wildcard host/analysis/_kernel/*) $(wildcard host/analysis/tactile/_kernel/*) $(wildcard host/analysis/motion/_kernel/*) $(wildcard protocol/_kernel/*)
	@echo "setting up $(VENV): uv $(UV_VERSION), then the project and its test tools (progress below)"
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --progress-bar on 'uv==$(UV_VERSION)'
	$(UV) pip install --python $(PY) -e '.[test,bench]'
	@du -sh $(VENV) | sed 's/^/installed: /'
	touch $@

# The bytecode cache, inside .venv. uv installs no .pyc files, and where the environment says not to
# write any (PYTHONDONTWRITEBYTECODE) every interpreter compiled every module it imported again at
# every start: 0.4 s of CPU to start `capsheet virtual` where 0.2 s is enough, 11 s for a tactile run
# where 7 s is. The suite starts ~400 of them. The cache lives in .venv (`make clean` takes it).
PYCACHE := PYTHONDONTWRITEBYTECODE= PYTHONPYCACHEPREFIX=$(abspath $(VENV))/pycache

demo: $(STAMP)
	$(PYCACHE) $(VENV)/bin/capsheet demo

test: $(STAMP)
	$(PYCACHE) $(PY) -m pytest -q -n 3 --dist loadgroup --durations=25

bench: $(STAMP)
	@for b in benchmarks/bench_*.py; do echo "== $$b"; $(PY) $$b || exit 1; done

clean:
	rm -rf $(VENV) build *.egg-info out firmware_ref/build firmware_ref/_capsheet_fw*

# --- firmware_ref (see firmware_ref/Makefile) -------------------------------------------------
.PHONY: firmware-check firmware-asan firmware-fuzz firmware-size firmware-qemu firmware-qemu-conformance firmware-board
firmware-check:   ## strict C99 builds, 64- and 32-bit, and the unit driver
	$(MAKE) -C firmware_ref check
firmware-asan:    ## decoder fuzz/replay driver under ASan+UBSan
	$(MAKE) -C firmware_ref asan
firmware-fuzz:    ## libFuzzer target (needs clang)
	$(MAKE) -C firmware_ref fuzz
firmware-size:    ## Cortex-M0+ flash/RAM (needs gcc-arm-none-eabi; installs nothing); also written to firmware_ref/build/size.md
	$(MAKE) -C firmware_ref size
firmware-qemu:    ## the firmware for QEMU mps2-an385 (needs gcc-arm-none-eabi, libnewlib-arm-none-eabi)
	$(MAKE) -C firmware_ref qemu
firmware-board:   ## the firmware for a NUCLEO-G0B1RE board (needs gcc-arm-none-eabi); flash/RAM in firmware_ref/build/board-size.md
	$(MAKE) -C firmware_ref board
firmware-qemu-conformance: $(STAMP) firmware-qemu  ## boot it in QEMU, run the whole conformance suite, non-zero on failure (SENSORS=accel+gyro[+mag]: a 6/9-axis chip)
	$(PY) -m firmware_ref.qemu conformance --runs $(or $(RUNS),1) --sensors $(or $(SENSORS),accel)
