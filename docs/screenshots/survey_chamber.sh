#!/usr/bin/env bash
# The survey's chamber comparison as a person sees it (issue 30, item 3): simulate the tutorial's
# fleet with chamber calibrations (docs/tutorials/fleet-survey.md, section 5), survey it, and
# capture report.html (one full-page PNG) and the recording's tabs in headless Chromium with
# make_screenshots.py. Look at every PNG: each device's plot of gyro bias against temperature
# with its chamber curve (units on both axes, the legend clear of the data).
#
#     bash docs/screenshots/survey_chamber.sh [OUT]    # default OUT: /tmp/survey_chamber
set -euo pipefail
out=${1:-/tmp/survey_chamber}
here=$(cd "$(dirname "$0")" && pwd)
mkdir -p "$out"
cd "$out"
imupipe simulate fleet --out chamber_fleet --set logs=5 --set log_s=100 --set events=false \
    --set chamber=true --seed 21
imupipe survey chamber_fleet --out chamber_survey --chamber chamber_fleet.chamber --force
python "$here/make_screenshots.py" chamber_survey/survey.rrd --html chamber_survey/report.html \
    --out shots --width 1100
