"""benchmarks/generative_unseen.py: the summary gives each set of new media its mean and
spread over the FID seeds, the seed-by-seed ratio to the true media and a row pooling every
set; bad arguments are the parser's errors (status 2), the sets and seeds checked before the run
folder, and nothing is written."""

from __future__ import annotations

import sys

import pytest

from benchmarks.common import append_rows, read_table
from benchmarks.generative_unseen import FIELDS, main, summary

pytestmark = pytest.mark.unit


def test_the_summary_gives_each_set_and_all_sets(tmp_path):
    table = tmp_path / "unseen.csv"
    rows = [  # (set, seed, FID of the set, FID of the truth), training sky; held-back 2x
        (1, 0, 66.0, 60.0), (0, 0, 55.0, 50.0), (0, 1, 57.0, 50.0), (1, 1, 60.0, 50.0)]
    for j, seed, fid, truth in rows:
        append_rows(table, FIELDS, [{
            "label": "run_a", "run": "/runs/a", "set": j, "first_seed": 16 + 2 * j,
            "seed": seed, "n": 2, "fid_train": fid, "fid_novel": 2 * fid,
            "fid_train_truth": truth, "fid_novel_truth": 2 * truth,
            "nearest_truth": 40.0 + j, "members_apart": 57.0}])
    text = summary(read_table(table)).splitlines()
    assert len(text) == 5  # header, rule, set 0, set 1, all
    assert text[2].startswith("| run_a | 0 | 2 | 56.0 ± 1.4 | 112.0 ± 2.8 | 50.0 ± 0.0 |")
    assert "| 1.10-1.14 | 1.10-1.14 | 40.0 ± 0.0 | 57.0 ± 0.0 |" in text[2]
    assert text[3].startswith("| run_a | 1 | 2 | 63.0 ± 4.2 |") and "| 1.10-1.20 |" in text[3]
    assert text[4].startswith("| run_a | all | 4 | 59.5 ± 4.8 |")
    assert "| 1.10-1.20 | 1.10-1.20 | 40.5 ± 0.6 |" in text[4]


@pytest.mark.parametrize("args, needle", [
    (["--from-run", "{tmp}/nowhere"], "--from-run"),
    (["--from-run", "{tmp}", "--sets", "a,b"], "comma-separated integers"),
    (["--from-run", "{tmp}", "--sets=-1"], "sets count from 0"),
])
def test_bad_arguments_are_refused_with_status_2(tmp_path, monkeypatch, capsys, args, needle):
    monkeypatch.setattr(sys, "argv", ["generative_unseen",
                                      *(a.format(tmp=tmp_path) for a in args)])
    with pytest.raises(SystemExit) as exit_:
        main()
    assert exit_.value.code == 2 and needle in capsys.readouterr().err
    assert not list(tmp_path.iterdir())
