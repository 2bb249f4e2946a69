#!/usr/bin/env bash
# Install blockray with its simulation, synthesis and test extras into .venv and run the tests.
source "$(dirname "$0")/_venv.sh" "[test]"
python -m pytest -m "not slow" "$@"
