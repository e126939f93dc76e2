#!/usr/bin/env bash
# For a GPU machine without network whose python has torch (with CUDA), numpy, pytest, typer,
# safetensors, tqdm and pyyaml but not the rest: run this on a machine with network to fetch the
# wheels that `bench/gpu.sh` needs besides those (the import closure of bench/plan.py,
# bench/train.py and tests/test_gpu.py), at this repository's uv.lock versions, into .whl/
# (git-ignored through .git/info/exclude; 38 MB). Copy .whl/ into the repository on the GPU
# machine; bench/gpu_env.sh installs them there. mujoco-studio (13 MB, the viewer) is left out:
# `import mujoco` loads its renderer only if present. A machine with network needs none of this:
# `uv sync` installs everything.
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
