#!/usr/bin/env bash
# Install blockray into .venv and render the built-in Cornell box: cornell.png, cornell.json.
source "$(dirname "$0")/_venv.sh" ""
blockray render "${1:-cornell}" --image "${1:-cornell}.png" --report "${1:-cornell}.json" "${@:2}"
echo "wrote ${1:-cornell}.png and ${1:-cornell}.json"
