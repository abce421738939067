# Two commands do all set-up on a fresh machine:
#   make demo   plan -> fly -> calibrate on the built-in simulator
#   make test   the test suite
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin

.PHONY: demo test install clean rtsp-deps

# The loopback RTSP server of the video tests and benchmark (tests/rtsp_server.py) is
# GStreamer's, from Debian packages; installed once, a no-op (one import) when present.
RTSP_PACKAGES := gir1.2-gst-rtsp-server-1.0 python3-gi gstreamer1.0-plugins-base gstreamer1.0-plugins-good \
	gstreamer1.0-plugins-bad gstreamer1.0-plugins-ugly gstreamer1.0-libav gstreamer1.0-x gstreamer1.0-tools
SUDO := $(shell [ "$$(id -u)" = 0 ] || echo sudo)

$(BIN)/dronecal-field: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	PYTHONWARNINGS=ignore $(BIN)/pip install --quiet -e '.[test]'  # no setuptools 'editable installation' screen
	touch $@

install: $(BIN)/dronecal-field

demo: install
	$(BIN)/dronecal-field demo --out demo-output

# apt waits up to 2 min for another apt (unattended-upgrades, a second make) to let go of its lock,
# and its ~300 lines go to a log: one line here, the log's tail if it fails.
APT_LOG := $(VENV)/apt-install.log
APT := $(SUDO) env DEBIAN_FRONTEND=noninteractive apt-get -o DPkg::Lock::Timeout=120 -o Acquire::Retries=3

rtsp-deps:
	@command -v gst-launch-1.0 >/dev/null && /usr/bin/python3 -c "import gi; gi.require_version('GstRtspServer', '1.0'); from gi.repository import Gst, GstRtspServer; Gst.init(None); assert all(Gst.ElementFactory.find(e) for e in ('x264enc', 'x265enc', 'rtph265pay', 'timeoverlay'))" 2>/dev/null \
	|| { echo "installing GStreamer's RTSP server for the video tests (apt-get, log in $(APT_LOG); waits up to 2 min if another apt is running)"; \
	     for i in 1 2 3 4 5 6 7 8; do $(APT) update -qq >$(APT_LOG) 2>&1 && break; grep -q "lock" $(APT_LOG) || break; echo "  apt is busy (another apt holds its lock): waiting 15 s"; sleep 15; done; \
	     $(APT) install -y -qq --no-install-recommends $(RTSP_PACKAGES) >>$(APT_LOG) 2>&1 \
	     || { tail -n 5 $(APT_LOG); echo "make test: apt-get could not install the RTSP test packages (above; full log $(APT_LOG)). If another apt holds the lock, let it finish and run make test again."; exit 1; }; }

test: install rtsp-deps
	$(BIN)/python -m pytest -q -n 2 --dist loadfile --no-loadscope-reorder --durations=25  # two workers, a module each, longest first (tests/conftest.py): most of the suite waits on real-time simulators and firmware

clean:
	rm -rf $(VENV) demo-output
