"""Generated episodes kept in chunks while a dataset is made (`pipeline.sources.episode_cache`):
a killed ingest resumes from them and writes the same file."""

import numpy as np
import pytest
import yaml
from safetensors.numpy import save_file
from typer.testing import CliRunner

import pipeline.sources.episode_cache as episode_cache
from cli import app
from pipeline.errors import UserError
from pipeline.sources.episode_cache import cached_episodes
from pipeline.sources.ogbench.generate import _Generator

runner = CliRunner()


def _episode(k: int) -> dict:
    rng = np.random.default_rng(k)
    return {
        "observations": rng.normal(size=(5 + k, 3)),
        "actions": rng.normal(size=(4 + k, 2)).astype(np.float32),
        "success": rng.random(4 + k) < 0.5,
        "p_stack": float(rng.random()),
        "xi": np.float64(rng.random()),
        "subtask": int(k),
    }


def _maker(log: list[int]):
    def make(indices):
        for k in indices:
            log.append(k)
            yield _episode(k)

    return make


def _same(a: dict, b: dict) -> None:
    assert list(a) == list(b)  # the same keys in the same order
    for key, x in a.items():
        y = b[key]
        if isinstance(x, np.ndarray):
            assert x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes()
        else:  # a NumPy scalar reads back as the Python number it holds
            plain = [v.item() if isinstance(v, np.generic) else v for v in (x, y)]
            assert plain[0] == plain[1] and type(plain[0]) is type(plain[1])


def test_kept_chunks_are_read_back_and_only_the_missing_ones_made(tmp_path):
    made: list[int] = []
    first = list(cached_episodes(_maker(made), 7, tmp_path, chunk=3))
    assert made == list(range(7)) and len(list(tmp_path.iterdir())) == 3
    for k, ep in enumerate(first):
        _same(_episode(k), ep)

    made.clear()
    again = list(cached_episodes(_maker(made), 7, tmp_path, chunk=3))
    assert made == []
    for a, b in zip(first, again, strict=True):
        _same(a, b)

    middle = sorted(tmp_path.iterdir())[1]
    data = middle.read_bytes()
    middle.write_bytes(data[: len(data) - 10])  # a write cut short: made again
    (tmp_path / sorted(p.name for p in tmp_path.iterdir())[2]).unlink()
    made.clear()
    resumed = list(cached_episodes(_maker(made), 7, tmp_path, chunk=3))
    assert made == [3, 4, 5, 6]
    for a, b in zip(first, resumed, strict=True):
        _same(a, b)


def test_without_a_folder_nothing_is_kept(tmp_path):
    made: list[int] = []
    assert len(list(cached_episodes(_maker(made), 4, None, chunk=2))) == 4 and made == [0, 1, 2, 3]


def test_a_foreign_chunk_is_made_again_and_a_damaged_one_is_a_one_line_error(tmp_path):
    list(cached_episodes(_maker([]), 2, tmp_path, chunk=2))
    (chunk,) = tmp_path.iterdir()
    save_file({"0.x": np.zeros(3)}, str(chunk), metadata={"episodes": '{"format": 99}'})
    made: list[int] = []
    assert len(list(cached_episodes(_maker(made), 2, tmp_path, chunk=2))) == 2 and made == [0, 1]
    chunk.write_bytes(b"not a safetensors file")
    with pytest.raises(UserError, match=f"{chunk}.*delete {tmp_path}"):
        episode_cache._read(chunk)


PARAMS = {
    "ingest": {
        "name": "gen",
        "source": "ogbench",
        "episodes": 6,
        "episode_steps": 101,
        "seed": 5,
        "ogbench": {"env_id": "pointmaze-medium-v0", "dataset_type": "navigate", "workers": 1},
    }
}


def test_a_killed_ingest_resumes_and_writes_the_same_file(tmp_path, monkeypatch):
    """Killed after two chunks of two episodes, the ingest run again makes only episodes 4
    and 5 and writes the MCAP an uninterrupted run writes, byte for byte; once it is written,
    the kept chunks are deleted."""
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(PARAMS))

    def ingest(data: str):
        args = ["ingest", "--params", str(tmp_path / "params.yaml"), "--data", str(tmp_path / data)]
        return runner.invoke(app, args)

    assert ingest("whole").exit_code == 0
    whole = (tmp_path / "whole/demos/gen.mcap").read_bytes()
    assert not any((tmp_path / "whole/scratch/ingest").rglob("*.safetensors"))

    monkeypatch.setattr(episode_cache, "CHUNK", 2)
    real_write, writes = episode_cache._write, []

    def write(path, episodes):
        if len(writes) == 2:
            raise KeyboardInterrupt  # killed while making the third chunk
        writes.append(path)
        real_write(path, episodes)

    monkeypatch.setattr(episode_cache, "_write", write)
    assert ingest("killed").exit_code != 0
    assert not (tmp_path / "killed/demos/gen.mcap").exists()
    assert len(list((tmp_path / "killed/scratch/ingest").rglob("*.safetensors"))) == 2

    monkeypatch.setattr(episode_cache, "_write", real_write)
    made: list[int] = []
    real_episode = _Generator.episode

    def episode(self, k):
        made.append(k)
        return real_episode(self, k)

    monkeypatch.setattr(_Generator, "episode", episode)
    result = ingest("killed")
    assert result.exit_code == 0, result.output
    assert made == [4, 5]
    assert (tmp_path / "killed/demos/gen.mcap").read_bytes() == whole
    assert not any((tmp_path / "killed/scratch/ingest").rglob("*.safetensors"))
