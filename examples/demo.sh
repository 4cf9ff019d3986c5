#!/usr/bin/env bash
# The demo: simulate lab sessions with a known truth, then calibrate them with imupipe.
# Writes examples/data/* (inputs + *.truth.json) and examples/out/* (every output).
set -euo pipefail
cd "$(dirname "$0")"
mkdir -p data
imupipe simulate static --rate 200 --duration 1800 --seed 1 --out data/static.csv
imupipe run demo.toml
echo "open the recording with: rerun examples/out/recording.rrd"
