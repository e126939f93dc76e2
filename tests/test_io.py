"""Atomic writes, the gap-free directory swap, umask permissions and output locks (io.py)."""

import json
import os
import subprocess
import sys

import pytest
import torch
from safetensors.torch import save_file

from pipeline import io as pio
from pipeline.errors import UserError
from pipeline.io import atomic_dir, atomic_path, output_lock, write_json


def test_atomic_dir_replaces_the_whole_directory(tmp_path):
    target = tmp_path / "resume"
    with atomic_dir(target) as tmp:
        (tmp / "a").write_text("old")
        (tmp / "only-old").write_text("x")
    with atomic_dir(target) as tmp:
        (tmp / "a").write_text("new")
    assert sorted(p.name for p in target.iterdir()) == ["a"]
    assert (target / "a").read_text() == "new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["resume"]  # nothing left beside it


def test_atomic_dir_keeps_the_old_directory_when_the_writer_fails(tmp_path):
    target = tmp_path / "resume"
    with atomic_dir(target) as tmp:
        (tmp / "a").write_text("old")
    with pytest.raises(RuntimeError), atomic_dir(target) as tmp:
        (tmp / "a").write_text("half")
        raise RuntimeError("killed")
    assert (target / "a").read_text() == "old"


def test_an_interruption_between_the_fallback_renames_loses_nothing(tmp_path, monkeypatch):
    """Without renameat2 the old directory is renamed aside first; an exception right after
    that puts it back before returning."""
    target = tmp_path / "resume"
    with atomic_dir(target) as tmp:
        (tmp / "a").write_text("old")
    monkeypatch.setattr(pio, "_exchange", lambda a, b: False)
    real_replace = os.replace
    calls = []

    def replace_then_die(src, dst):
        calls.append((src, dst))
        real_replace(src, dst)
        if len(calls) == 1:  # the old directory is aside, the new one not yet in place
            raise KeyboardInterrupt

    monkeypatch.setattr(pio.os, "replace", replace_then_die)
    with pytest.raises(KeyboardInterrupt), atomic_dir(target) as tmp:
        (tmp / "a").write_text("new")
    assert str(calls[0][1]).endswith(".old-resume")  # it did die between the two renames
    assert (target / "a").read_text() == "old"


def test_a_sigkill_between_the_fallback_renames_is_recovered_by_the_reader(tmp_path):
    """A SIGKILL runs no cleanup: what it leaves is the old directory under its aside name."""
    from pipeline.training.state import read_progress

    target = tmp_path / "resume"
    with atomic_dir(target) as tmp:
        (tmp / "state.json").write_text(json.dumps({"fingerprint": "f", "progress": {"step": 7}}))
    os.replace(target, tmp_path / ".old-resume")
    assert read_progress(target, "f").step == 7
    assert (target / "state.json").exists() and not (tmp_path / ".old-resume").exists()


def test_the_exchange_is_atomic_on_this_filesystem(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    a.mkdir()
    b.mkdir()
    (a / "f").write_text("a")
    (b / "f").write_text("b")
    if not pio._exchange(a, b):
        pytest.skip("this filesystem has no RENAME_EXCHANGE; the fallback path is tested above")
    assert (a / "f").read_text() == "b" and (b / "f").read_text() == "a"


def test_written_files_and_directories_follow_the_umask(tmp_path):
    old = os.umask(0o022)
    try:
        write_json(tmp_path / "x.json", {"a": 1})
        with atomic_path(tmp_path / "y.bin") as tmp:
            tmp.write_bytes(b"1")
        with atomic_dir(tmp_path / "d") as tmp:
            (tmp / "f").write_text("1")
        # safetensors' save_file creates its file owner-only (0600), in a file or a directory:
        with atomic_path(tmp_path / "w.safetensors") as tmp:
            save_file({"w": torch.ones(2)}, tmp)
        with atomic_dir(tmp_path / "m") as tmp:
            save_file({"w": torch.ones(2)}, tmp / "model.safetensors")
    finally:
        os.umask(old)
    assert (tmp_path / "w.safetensors").stat().st_mode & 0o777 == 0o644
    assert (tmp_path / "m" / "model.safetensors").stat().st_mode & 0o777 == 0o644
    assert (tmp_path / "x.json").stat().st_mode & 0o777 == 0o644
    assert (tmp_path / "y.bin").stat().st_mode & 0o777 == 0o644
    assert (tmp_path / "d").stat().st_mode & 0o777 == 0o755
    assert json.loads((tmp_path / "x.json").read_text()) == {"a": 1}


def test_a_second_writer_of_one_output_is_refused_with_the_holders_pid(tmp_path):
    model = tmp_path / "models" / "m"
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys, time\n"
            "from pipeline.io import output_lock\n"
            f"with output_lock({str(model)!r}):\n"
            "    print('locked', flush=True)\n"
            "    time.sleep(60)\n",
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout.readline().strip() == "locked"
        with pytest.raises(UserError, match=rf"PID {holder.pid}\b"), output_lock(model):
            pass
    finally:
        holder.kill()
        holder.wait()
    with output_lock(model):  # released by the kernel when the holder died
        pass
