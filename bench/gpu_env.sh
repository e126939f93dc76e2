# Sourced by the GPU scripts (bench/gpu.sh, bench/gpu_ant.sh) from the repo root (PY: python3 if unset):
# installs the wheels in .whl/, if any (bench/gpu_wheels.sh: for a machine without network), into
# /tmp/oposm-site and puts them and this repository on PYTHONPATH for "$PY".
PY=${PY:-${PYTHON:-python3}}  # also when sourced by hand, e.g. before resuming a training
if compgen -G ".whl/*.whl" >/dev/null; then
    "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
        --target /tmp/oposm-site .whl/*.whl || exit 1
    export PYTHONPATH=/tmp/oposm-site
fi
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1 MUJOCO_GL=egl
