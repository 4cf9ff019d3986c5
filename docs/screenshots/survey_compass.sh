#!/usr/bin/env bash
# The compass section of `imupipe survey`'s report.html, rendered in headless Chromium to look at:
# three simulated vehicles (two ArduPilot, one PX4) of five flights each, the hard iron of ap2
# jumping by 10 % of the field from its flight 3 on (the fleet of tests/test_survey_compass.py).
#   bash docs/screenshots/survey_compass.sh [WORKDIR]   -> WORKDIR/shots/report.png
set -euo pipefail
work=${1:-$(mktemp -d)}
here=$(cd "$(dirname "$0")" && pwd)
python - "$work" <<'PY'
import sys
from pathlib import Path

sys.path.insert(0, str(Path("tests").resolve()))
from test_survey_compass import write_fleet  # noqa: E402

write_fleet(Path(sys.argv[1]) / "logs", planted=True)
PY
imupipe survey "$work/logs" --out "$work/out" --no-rerun --force
python "$here/make_screenshots.py" --html "$work/out/report.html" --out "$work/shots" --width 1100
