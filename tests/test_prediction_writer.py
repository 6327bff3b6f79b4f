"""predictions.npz written while evaluate counts (entry.PredictionWriter): the same arrays as the archive written
at the end (entry.write_predictions), nothing left behind when a write fails or the stage stops, and a failed
write raised to the stage, not lost on the writer's thread."""
from __future__ import annotations

import errno
import os

import numpy as np
import pytest

from pairedgta.evaluation import entry

CONDITIONS = ["Day-Sunny", "Night-Rain", "Dusk-Fog"]


def groups(n: int = 7, h: int = 32, w: int = 48) -> list[dict]:
    rng = np.random.default_rng(0)
    out = []
    for g in range(n):
        present = CONDITIONS if g % 3 else CONDITIONS[:2]  # a group without one condition: 255 / 0 there
        out.append({"group_id": f"{g:04d}",
                    "pred": {c: rng.integers(0, 19, (h, w), dtype=np.uint8) for c in present},
                    "conf": {c: rng.integers(0, 256, (h // 2, w // 2), dtype=np.uint8) for c in present}})
    return out


def load(path) -> dict[str, np.ndarray]:
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def test_the_streamed_archive_holds_what_the_archive_written_at_the_end_holds(tmp_path):
    results = groups()
    entry.write_predictions(tmp_path / "end.npz", results, CONDITIONS)
    writer = entry.PredictionWriter(tmp_path / "predictions.npz", CONDITIONS, ahead=10_000)
    for r in results:
        writer.add(r["group_id"], r["pred"], r["conf"])
    assert not (tmp_path / "predictions.npz").exists()  # under its temporary name until closed
    writer.close([r["group_id"] for r in results])
    streamed, end = load(tmp_path / "predictions.npz"), load(tmp_path / "end.npz")
    assert sorted(streamed) == sorted(end)
    for k in end:
        np.testing.assert_array_equal(streamed[k], end[k], err_msg=k)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["end.npz", "predictions.npz"]
    labels, conf = entry.read_prediction(tmp_path / "predictions.npz", "0001", "Dusk-Fog")
    np.testing.assert_array_equal(labels, results[1]["pred"]["Dusk-Fog"])
    assert entry.read_prediction(tmp_path / "predictions.npz", "0000", "Dusk-Fog") is None  # absent there


def test_closing_with_other_groups_than_were_written_is_refused(tmp_path):
    results = groups(3)
    writer = entry.PredictionWriter(tmp_path / "predictions.npz", CONDITIONS)
    for r in results:
        writer.add(r["group_id"], r["pred"], r["conf"])
    with pytest.raises(RuntimeError, match="not the entry's"):
        writer.close([r["group_id"] for r in reversed(results)])
    writer.abort()
    assert list(tmp_path.iterdir()) == []


def test_a_write_that_fails_on_the_writers_thread_reaches_the_stage_and_leaves_nothing(tmp_path, monkeypatch):
    writes = []

    def full(self, name, array):
        writes.append(name)
        if len(writes) > 3:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(entry.PredictionWriter, "_member", full)
    writer = entry.PredictionWriter(tmp_path / "predictions.npz", CONDITIONS, ahead=0)
    with pytest.raises(OSError) as caught:
        for r in groups():
            writer.add(r["group_id"], r["pred"], r["conf"])
        writer.close([r["group_id"] for r in groups()])
    assert caught.value.errno == errno.ENOSPC
    writer.abort()
    assert list(tmp_path.iterdir()) == []
