#!/usr/bin/env bash
# Create ./.venv if it is missing and install beacon-torch (editable) with its test extras.
set -euo pipefail
cd "$(dirname "$0")/.."
python=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$python" -m venv .venv
# torch first, exactly this version: it is the local CPU wheel on these machines, and any
# looser requirement would make pip fetch a CUDA build of several GB.
.venv/bin/python -m pip install --quiet --disable-pip-version-check torch==2.13.0
.venv/bin/python -m pip install --quiet --disable-pip-version-check -e '.[test]'
