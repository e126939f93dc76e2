#!/usr/bin/env bash
# Fetch (here, with network) the wheels `bench/gpu.sh` needs on the GPU machine, whose image has
# torch, numpy, pytest, typer, safetensors, tqdm, pyyaml but not these (the import closure of
# bench/plan.py, bench/train.py and tests/test_gpu.py, less the image's packages). Versions: this
# repo's uv.lock. They go to .whl/ (git-ignored through .git/info/exclude) and travel with
# `carry=[".whl", ...]`; the device tool carries at most 64 MiB in all: these 38 MB, the default
# model (2 MB), its segments (14 MB) and the tree (2 MB) fit. mujoco-studio (13 MB, the viewer) is
# left out: `import mujoco` loads its renderer only if present.
set -euo pipefail
cd "$(dirname "$0")/.."
grep -qx '/.whl/' .git/info/exclude 2>/dev/null || echo /.whl/ >> "$(git rev-parse --git-common-dir)/info/exclude"
PY=${PYTHON:-python3}
version() {  # the locked version of a package
    awk -v name="$1" '$0 == "name = \"" name "\"" {getline; gsub(/version = |"/, ""); print; exit}' uv.lock
}
# --ant: the ant chain's set instead (`bench/gpu_ant.sh`): no gymnasium-robotics (26 MB, not
# imported there), plus OGBench, MCAP and dvclive's import closure; 33 MB. A new set replaces
# the old one in .whl/.
names="mujoco mujoco-core gymnasium gymnasium-robotics farama-notifications pydantic
    pydantic-core annotated-types typing-inspection glfw pettingzoo"
if [ "${1:-}" = --ant ]; then
    names="${names/gymnasium-robotics/} ogbench mcap mcap-protobuf-support lz4 zstandard dvclive
        dvc dvc-render dvc-studio-client flatten-dict funcy pytz ruamel-yaml voluptuous wcwidth
        scmrepo diskcache dpath dvc-data dvc-http dvc-objects flufl-lock orjson atpublic pygtrie
        sqltrie zc-lockfile platformdirs configobj"
fi
rm -rf .whl
mkdir -p .whl
for name in $names; do
    v=$(version "$name")
    [ -n "$v" ] || { echo "$name is not in uv.lock"; continue; }
    "$PY" -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 \
        --implementation cp --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 \
        --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 -d .whl "$name==$v"
done
if [ "${1:-}" = --ant ]; then  # dvclive's git backend: its pure-Python wheel
    "$PY" -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 \
        --implementation py --platform any -d .whl "dulwich==$(version dulwich)"
fi
du -sh .whl
