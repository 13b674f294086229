# Two commands a newcomer needs: `make demo` (set up, then run the main job) and
# `make test` (set up, then run the whole test suite). Both create ./.venv on first use.
VENV   ?= .venv
PYTHON ?= python3
# The ROS wheels re-execute Python with their own LD_LIBRARY_PATH; a value leaking in from
# another virtualenv breaks rclpy (../shared/ROS2_ON_PIP.md), so clear both for every call.
RUN    := env -u _ROS_WHEELS_BOOTSTRAP_COMPLETE -u LD_LIBRARY_PATH ROS_AUTOMATIC_DISCOVERY_RANGE=OFF
STAMP  := $(VENV)/.brepose-installed

.PHONY: setup test demo bench clean

setup: $(STAMP)

$(STAMP): setup.py setup.cfg package.xml
	$(PYTHON) -m venv $(VENV)
	$(RUN) $(VENV)/bin/python -m pip install --quiet --upgrade pip
	$(RUN) $(VENV)/bin/python -m pip install --quiet -e '.[ros,compile,learn,test]'
	touch $@

test: $(STAMP)
	$(RUN) $(VENV)/bin/python -m pytest -q test

demo: $(STAMP)
	$(RUN) $(VENV)/bin/python launch_free_scripts/demo.py --out out/demo

bench: $(STAMP)
	$(RUN) $(VENV)/bin/python bench/compile.py

clean:
	rm -rf $(VENV) out build *.egg-info
