#!/usr/bin/env bash
# Install blockray with its simulation, synthesis and test extras into .venv and run the tests,
# one pytest-xdist worker per core, each test file on one worker (its module fixtures and builds
# made once).
source "$(dirname "$0")/_venv.sh" "[test]"
python -m pytest -m "not slow" -n auto --dist loadfile "$@"
