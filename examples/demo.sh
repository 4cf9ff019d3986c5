#!/usr/bin/env bash
# The demo: simulate lab sessions with a known truth (each FILE gets FILE.truth.json), calibrate
# them with `imupipe run`, then apply the calibration to a small "fleet" with `imupipe convert`.
# Writes examples/data/* (inputs) and examples/out/* (every output).
set -euo pipefail
cd "$(dirname "$0")"
rm -rf data out
mkdir -p data/fleet
echo "== simulating lab sessions"
imupipe simulate static  --rate 100 --duration 7200 --seed 1 --out data/static.mcap   # 2 h at rest (MCAP)
imupipe simulate poses   --seed 2 --out data/poses.csv                                # multi-position session
imupipe simulate mag     --seed 3 --out data/tumble.bag                               # magnetometer tumbling (ROS 1 bag)
imupipe simulate thermal --seed 4 --out data/chamber.csv                              # chamber cycles at 1 and 0.5 degC/min
imupipe simulate thermal --seed 5 --set 'heating_rates=[2.0]' --out data/check.mcap  # held-out cycle at 2 degC/min
echo "== calibrating: imupipe run demo.toml"
imupipe run demo.toml
echo "== a small fleet: imupipe convert"
imupipe simulate static --duration 60 --seed 6 --out data/fleet/robot1.mcap
imupipe simulate static --duration 60 --seed 7 --out data/fleet/robot2.bag
imupipe simulate static --duration 60 --seed 8 --out data/fleet/robot3               # ROS 2 bag folder
imupipe convert --calibration out/calibration.json --out out/fleet --jobs 2 data/fleet
echo
echo "outputs in examples/out/; open the recording with: rerun examples/out/recording.rrd"
echo "(no display: rerun --web-viewer examples/out/recording.rrd, or open examples/out/report.html)"
