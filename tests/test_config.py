import os
import time
from pathlib import Path

import pytest
import torch
from factories import skill_model_config, train_updater

from pipeline.config import Params, load_params
from pipeline.errors import UserError

ROOT = Path(__file__).resolve().parents[1]


def _write(tmp_path, text):
    path = tmp_path / "params.yaml"
    path.write_text(text)
    return path


def test_params_yaml_is_valid_and_complete():
    """Every field is spelled out in the base: dvc.yaml templates and `dvc exp run -S` need them.
    The variants (params-*.yaml) are overlays holding only what differs from their base
    (tests/test_params_overlays.py)."""
    params = load_params(ROOT / "params.yaml")
    import yaml

    raw = yaml.safe_load((ROOT / "params.yaml").read_text())

    def keys(d, prefix=""):
        out = set()
        for k, v in d.items():
            out.add(prefix + k)
            if isinstance(v, dict):
                out |= keys(v, prefix + k + ".")
        return out

    assert keys(raw) == keys(params.model_dump())


def test_params_yaml_holds_exactly_the_config_defaults():
    """The config classes are the single source of defaults: deleting a key from params.yaml must
    not change a run, so every value there equals the class default (and no key is missing)."""
    import yaml

    assert yaml.safe_load((ROOT / "params.yaml").read_text()) == Params().model_dump(mode="json")


def test_validate_section_keeps_its_name_without_shadowing_pydantic(tmp_path):
    params = load_params(_write(tmp_path, "validate:\n  starts: 7\n"), ["validate.skills=2"])
    assert (params.validation.starts, params.validation.skills) == (7, 2)
    assert params.model_dump()["validate"]["starts"] == 7
    assert "validate" not in Params.model_fields  # a field of that name shadows BaseModel.validate
    with pytest.raises(UserError, match=r"unknown key 'validate\.startz'.*particles"):
        load_params(_write(tmp_path, "validate:\n  startz: 3\n"))
    with pytest.raises(
        UserError, match="valid keys here: .*dynamics, bc, gcbc, value, validate, deploy"
    ):
        load_params(_write(tmp_path, "valdate: {}\n"))


def test_unknown_key_names_the_key_and_the_valid_ones(tmp_path):
    with pytest.raises(UserError, match=r"unknown key 'ingest\.expert\.pgain'.*p_gain"):
        load_params(_write(tmp_path, "ingest:\n  expert:\n    pgain: 3\n"))


def test_unknown_section_is_an_error(tmp_path):
    with pytest.raises(UserError, match="unknown key 'ingst'"):
        load_params(_write(tmp_path, "ingst: {}\n"))


def test_wrong_type_names_the_key(tmp_path):
    with pytest.raises(UserError, match=r"'ingest\.episodes'.*integer"):
        load_params(_write(tmp_path, "ingest:\n  episodes: many\n"))


def test_split_fractions_must_sum_to_one(tmp_path):
    with pytest.raises(UserError, match="sum to 1"):
        load_params(_write(tmp_path, "segment:\n  split: {train: 0.5, validation: 0.1, test: 0}\n"))


def test_overrides_apply_for_one_run_and_are_validated(tmp_path):
    path = _write(tmp_path, "segment:\n  window: 40\n")
    params = load_params(path, ["segment.window=12", "ingest.expert.action_noise=0.1"])
    assert params.segment.window == 12 and params.ingest.expert.action_noise == 0.1
    assert load_params(path).segment.window == 40
    with pytest.raises(UserError, match="unknown key 'segment.windw'"):
        load_params(path, ["segment.windw=3"])
    with pytest.raises(UserError, match="section.key=value"):
        load_params(path, ["segment.window"])


def test_missing_and_malformed_files(tmp_path):
    with pytest.raises(UserError, match="not found"):
        load_params(tmp_path / "nope.yaml")
    with pytest.raises(UserError, match="not valid YAML"):
        load_params(_write(tmp_path, "ingest: [\n"))
    text = "ingest:\n  episodes: 3\n seed: 1\n"  # line 3: bad indentation
    with pytest.raises(UserError, match=r"not valid YAML: line 3, column 2: expected <block end>"):
        load_params(_write(tmp_path, text))


def test_defaults_match_the_paper_window():
    assert Params().segment.window == 40


def test_paper_params_hold_the_papers_tables():
    paper = load_params(ROOT / "params-paper.yaml")
    assert (paper.train.z_dim, paper.train.hidden, paper.train.batch_size) == (256, 256, 100)
    assert paper.train.lr_e == paper.train.lr_m == 5e-5 and paper.segment.window == 40


def test_auto_threads_use_every_core_only_on_an_idle_machine(monkeypatch):
    """train.threads: auto -> all cores when nothing else is runnable, else one thread."""
    import os

    from pipeline import devices

    assert isinstance(devices.runnable_others(samples=2, interval_s=0.0), int)  # Linux
    monkeypatch.setattr(devices, "runnable_others", lambda: 0)
    assert devices.auto_threads("auto") == (os.cpu_count() or 1)
    monkeypatch.setattr(devices, "runnable_others", lambda: 2)
    assert devices.auto_threads("auto") == 1
    assert devices.auto_threads(3) == 3 and devices.auto_threads(None) is None


def test_auto_threads_follow_other_jobs_during_a_run_after_two_equal_looks(monkeypatch):
    """A run that started alone gives up the second core once another job runs (two looks in
    a row), and takes it back once that job ends; fixed settings are never changed."""
    import os

    from pipeline import devices

    cores = os.cpu_count() or 1
    seen = iter([0, 1, 0, 1, 1, 0, 0])
    previous = torch.get_num_threads()
    with devices.AutoThreads("auto", recheck_s=0.0, probe=lambda: next(seen)) as threads:
        assert torch.get_num_threads() == cores
        threads.tick()  # 1 other: not yet
        assert torch.get_num_threads() == cores
        threads.tick()  # 0: the pending switch is dropped
        threads.tick()
        threads.tick()  # 1, 1: switch
        assert torch.get_num_threads() == 1
        threads.tick()
        threads.tick()  # 0, 0: back
        assert torch.get_num_threads() == cores
        assert threads.switches == (2 if cores > 1 else 0)
    assert torch.get_num_threads() == previous
    with devices.AutoThreads(1, recheck_s=0.0, probe=lambda: 0) as threads:
        threads.tick()
        threads.tick()
        assert torch.get_num_threads() == 1


def test_runnable_others_sees_a_busy_process_and_not_this_ones_threads():
    import subprocess
    import sys

    from pipeline import devices

    assert devices._own_running() >= 1  # the reading thread itself
    busy = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        deadline = time.monotonic() + 30  # until the busy process is scheduled, not a fixed wait
        while devices.runnable_others(samples=10) < 1:
            assert time.monotonic() < deadline, "a busy process never counted as runnable"
    finally:
        busy.kill()
        busy.wait()


def _em_parameters_after_steps(threads: int, dtype: str, batch: int, window: int, hidden: int):
    """The parameters after 2 EM steps from seed 0 on `threads` torch threads."""
    from pipeline.model import SkillModel
    from pipeline.training.data import WindowBatch

    torch.set_num_threads(threads)
    torch.manual_seed(0)
    model = SkillModel(skill_model_config(4, 2, z_dim=16, hidden=hidden))
    updater = train_updater(model, lr_e=1e-3, lr_m=1e-3, e_prior="current", dtype=dtype)
    generator = torch.Generator().manual_seed(1)
    states = torch.randn(batch, window, 4, generator=generator)
    actions = torch.randn(batch, window - 1, 2, generator=generator)
    for _ in range(2):
        updater.step(WindowBatch(states, actions))
    return [p.detach().clone() for p in model.parameters()]


@pytest.mark.parametrize(
    "dtype, batch, window, hidden",
    [("float32", 64, 11, 128), ("float32", 100, 40, 128), ("float32", 100, 40, 256)],
    ids=["small", "main-job", "paper-hidden"],
)
def test_training_numbers_do_not_depend_on_the_thread_count(dtype, batch, window, hidden):
    """What makes `train.threads` a speed choice only: an EM step gives the same bits on 1, 2
    and 3 threads, at the main job's sizes (batch 100 x window 40, where MKL's default splits
    the weight gradients' sums between threads) and the paper's hidden size (`cpu_math`)."""
    from pipeline import cpu_math

    assert cpu_math.ensure().endswith("STRICT")
    previous = torch.get_num_threads()
    try:
        first, *others = [
            _em_parameters_after_steps(t, dtype, batch, window, hidden) for t in (1, 2, 3)
        ]
    finally:
        torch.set_num_threads(previous)
    for other in others:
        assert all(torch.equal(a, b) for a, b in zip(first, other, strict=True))


def test_cpu_math_mode_is_strict_and_its_default_follows_the_cpu(tmp_path):
    """pipeline/__init__.py starts MKL in a strict reproducible mode: on an Intel CPU AVX-512's
    branch where it has it, AVX2's where it has only that; MKL's own choice elsewhere (other
    vendors' CPUs, where MKL takes no named branch: read back as AUTO on an AMD EPYC)."""
    from pipeline import cpu_math

    assert cpu_math.mode() == os.environ["MKL_CBWR"].upper()
    cases = {("GenuineIntel", "fpu avx2 avx512f avx512bw"): "AVX512,STRICT",
             ("GenuineIntel", "fpu sse4_2 avx avx2 fma"): "AVX2,STRICT",
             ("GenuineIntel", "fpu sse2"): "AUTO,STRICT",
             ("AuthenticAMD", "fpu avx2 avx512f avx512bw"): "AUTO,STRICT"}  # fmt: skip
    for (vendor, flags), expected in cases.items():
        (tmp_path / "cpuinfo").write_text(f"vendor_id\t: {vendor}\nflags\t\t: {flags}\n")
        assert cpu_math.default_mode(tmp_path / "cpuinfo") == expected
    assert cpu_math.default_mode(tmp_path / "absent") == "AUTO,STRICT"


def test_bfloat16_or_no_strict_mode_keeps_auto_threads_on_one():
    """Where threads would change the bits (bfloat16's oneDNN kernels on CPU), `auto` is one
    thread whatever the load; float32 on CPU and any GPU work follow the load."""
    from pipeline import cpu_math, devices

    assert cpu_math.numerics_follow_threads("cpu", "bfloat16")
    assert not cpu_math.numerics_follow_threads("cpu", "float32")
    assert not cpu_math.numerics_follow_threads("cuda", "bfloat16")
    assert devices.auto_threads("auto", probe=lambda: 0, fixed_numerics=False) == 1
    previous = torch.get_num_threads()
    with devices.AutoThreads("auto", recheck_s=0.0, probe=lambda: 0, fixed_numerics=False) as t:
        t.tick()
        t.tick()
        assert torch.get_num_threads() == 1 and t.switches == 0
    assert torch.get_num_threads() == previous


def test_auto_dtype_is_bfloat16_only_on_a_cpu_that_multiplies_it(tmp_path):
    """`train.dtype: auto`: bfloat16 where /proc/cpuinfo lists amx_bf16 (AVX512-BF16 alone was
    measured slower than float32), float32 on other CPUs and on GPUs; a set dtype is kept."""
    from pipeline.training import updaters

    cpu, gpu = torch.device("cpu"), torch.device("cuda")
    with_bf16, without = tmp_path / "with", tmp_path / "without"
    with_bf16.write_text("flags\t\t: fpu avx512f avx512_bf16 amx_bf16 amx_tile\n")
    without.write_text("flags\t\t: fpu avx2 avx512f avx512bw avx512_bf16\n")
    assert updaters.native_bfloat16(with_bf16) and not updaters.native_bfloat16(without)
    assert not updaters.native_bfloat16(tmp_path / "missing")  # no /proc: no claim
    assert updaters.resolve_dtype("auto", cpu, native=True) == "bfloat16"
    assert updaters.resolve_dtype("auto", cpu, native=False) == "float32"
    assert updaters.resolve_dtype("auto", gpu, native=True) == "float32"
    assert updaters.resolve_dtype("float32", cpu, native=True) == "float32"
    assert updaters.resolve_dtype("bfloat16", cpu, native=False) == "bfloat16"
