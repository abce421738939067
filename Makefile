# Two commands do all set-up on a fresh machine:
#   make demo   plan -> fly -> calibrate on the built-in simulator
#   make test   the test suite
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin

.PHONY: demo test install clean

$(BIN)/dronecal-field: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[test]'
	touch $@

install: $(BIN)/dronecal-field

demo: install
	$(BIN)/dronecal-field demo --out demo-output

test: install
	$(BIN)/python -m pytest -q

clean:
	rm -rf $(VENV) demo-output
