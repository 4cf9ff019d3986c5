#!/usr/bin/env bash
# The compass section of `imupipe survey`'s report.html, rendered in headless Chromium to look at:
# three simulated vehicles (two ArduPilot, one PX4) of five flights each, the hard iron of ap2
# jumping by 10 % of the field from its flight 3 on (the fleet of tests/test_survey_compass.py).
#   bash docs/screenshots/survey_compass.sh [WORKDIR]   -> WORKDIR/shots/report.png
#   bash docs/screenshots/survey_compass.sh WORKDIR --rerun   -> also the recording's tabs
#     (WORKDIR/shots/00_Summary.png, 01_survey.png...: Rerun's web viewer, headless)
set -euo pipefail
work=${1:-$(mktemp -d)}
rerun=${2:-}
here=$(cd "$(dirname "$0")" && pwd)
python - "$work" <<'PY'
import sys
from pathlib import Path

sys.path.insert(0, str(Path("tests").resolve()))
from test_survey_compass import write_fleet  # noqa: E402

write_fleet(Path(sys.argv[1]) / "logs", planted=True)
PY
if [ "$rerun" = "--rerun" ]; then
  imupipe survey "$work/logs" --out "$work/out" --force
  python "$here/make_screenshots.py" "$work/out/survey.rrd" --html "$work/out/report.html" \
    --out "$work/shots" --width 1100
else
  imupipe survey "$work/logs" --out "$work/out" --no-rerun --force
  python "$here/make_screenshots.py" --html "$work/out/report.html" --out "$work/shots" --width 1100
fi
