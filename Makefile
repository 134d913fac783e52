# Set-up and run targets. Each creates .venv if missing and installs the package into it.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP_RUN := $(VENV)/.stamp-run
STAMP_TEST := $(VENV)/.stamp-test

.PHONY: demo test bench data-extra fuzz lint clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip

$(STAMP_RUN): pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install -q -e .
	touch $@

$(STAMP_TEST): pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install -q -e '.[test]'
	touch $@ $(STAMP_RUN)

demo: $(STAMP_RUN)
	$(BIN)/cgamap demo

test: $(STAMP_TEST)
	$(BIN)/ruff check .
	$(BIN)/python -m pytest -m "not slow"

bench: $(STAMP_TEST)
	$(BIN)/python -m bench.run --out bench/results.json

# real data beyond ../shared/data (the MIT Killian Court log), into $$CGAMAP_EXTRA_DATA or
# ~/.cache/cgamap/data: bench_mapping_killian reads it from there (bench_mapping_csail reads
# the MIT CSAIL log there too, when someone put it there: no package ships it)
data-extra: $(STAMP_TEST)
	$(BIN)/python -m bench.extra_data

fuzz: $(STAMP_TEST)
	CGAMAP_FUZZ_EXAMPLES=200000 $(BIN)/python -m pytest -m slow tests -k fuzz

lint: $(STAMP_TEST)
	$(BIN)/ruff check .

clean:
	rm -rf $(VENV) build *.egg-info

# --- the daemon as a systemd service (run as root on the robot) --------------------------
PREFIX_UNIT ?= /etc/systemd/system
UDEV_RULES ?= /etc/udev/rules.d
CONF_DIR ?= /etc/cgamap
SERVICE_USER ?= cgamap

.PHONY: install-service soak
install-service: $(STAMP_RUN)
	@for p in "$(abspath $(BIN))" "$$(readlink -f $(BIN)/python)"; do case "$$p" in \
	/home/*|/root/*) echo "install-service: $$p is under /home or /root, which the unit \
	hides (ProtectHome=yes): use a Python and a clone outside them (/usr, /opt, /srv)" >&2; \
	exit 1;; esac; done
	$(BIN)/cgamapd --check-config config/robot.yaml
	getent group plugdev >/dev/null || groupadd --system plugdev
	getent passwd $(SERVICE_USER) >/dev/null || useradd --system --user-group \
		--home-dir /var/lib/cgamap --no-create-home --shell /usr/sbin/nologin \
		--groups dialout,plugdev $(SERVICE_USER)
	install -d -m 0755 $(CONF_DIR)
	for f in robot.yaml hand_eye.yaml; do \
		[ -e $(CONF_DIR)/$$f ] || install -m 0644 config/$$f $(CONF_DIR)/$$f; done
	sed -e 's|/usr/local/bin/cgamapd|$(abspath $(BIN))/cgamapd|g' \
		-e 's|/etc/cgamap/|$(CONF_DIR)/|g' systemd/cgamapd.service > $(PREFIX_UNIT)/cgamapd.service
	install -m 0644 systemd/99-cgamap-serial.rules $(UDEV_RULES)/99-cgamap-serial.rules
	-udevadm control --reload-rules && udevadm trigger --subsystem-match=usb-serial
	-systemctl daemon-reload
	@echo "installed; start with: systemctl enable --now cgamapd"

# >= 200 SIGKILLs of cgamapd (and of the bare store) while checkpointing
soak: $(STAMP_TEST)
	$(BIN)/python -m pytest -m slow -k soak tests/test_store.py tests/test_daemon_faults.py
