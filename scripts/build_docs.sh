#!/usr/bin/env bash
# Build the documentation site (docs/*.md through MyST, API pages from the docstrings) into
# docs/_build/html. Needs the docs extra: pip install -e '.[docs]'
set -euo pipefail
cd "$(dirname "$0")/.."
python3 -m sphinx -b html -q docs docs/_build/html "$@"
echo "docs: $(pwd)/docs/_build/html/index.html"
