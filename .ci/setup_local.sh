#!/usr/bin/env bash
# CI from scratch on a fresh Debian 12 machine with Python 3.11 (python3.11-venv) and node 20:
# install the service with its test extra, the glTF validator, then run the test suite.
set -euo pipefail
cd "$(dirname "$0")/.."

PYTHON="${PYTHON:-$(command -v python3.11 || command -v python3)}"
"$PYTHON" -c 'import sys; assert sys.version_info >= (3, 11), sys.version'
node -e 'if (+process.versions.node.split(".")[0] < 20) { throw new Error("node >= 20 needed"); }'

"$PYTHON" -m venv --clear .venv
.venv/bin/python -m pip install --upgrade pip
.venv/bin/python -m pip install -e ".[test]"   # no torch/anny: the `build` extra is optional
npm ci                                         # gltf-validator (devDependency) for the GLB tests

# The body-model build's own dependencies (torch CPU wheel first, then anny), so the seeded
# smoke build in tests/test_build_smoke.py runs rather than skips.
.venv/bin/python -m pip install torch==2.13.0
.venv/bin/python -m pip install -e ".[test,build]"

# Debian's chromium for the customer page's end-to-end test (driven by playwright-core from npm;
# never `playwright install`), and SuiteSparse for CHOLMOD (the `fast` extra: scikit-sparse).
apt-get update && apt-get install -y chromium libsuitesparse-dev
.venv/bin/python -m pip install -e ".[test,build,fast]"

