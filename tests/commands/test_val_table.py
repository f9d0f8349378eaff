"""The val table (denoiser/commands/tools/val_table.py over conf/val_table.yaml): training candidates
compared on validation splits, from small synthetic metrics.csv files: the means against a hand
computation, the paired intervals' verdicts, the per-sequence seed averages against a plain loop,
seeds outside ``seeds`` left out, and a missing seed as one error line naming the file and group."""

from __future__ import annotations

import csv
import re
import statistics
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from denoiser.conf import CONF_DIR
from denoiser.errors import UserError

FIELDS = ["method", "scene", "sequence", "frames", "psnr", "psnr_all", "psnr_f2"]
SEQUENCES = ["val/a_000", "val/b_000", "val/c_000", "val/d_000"]
#: psnr_f2 per sequence of the reference's seeds (different per seed: the averaging matters)
BASE = {0: [27.1, 28.3, 26.9, 30.2], 1: [27.7, 28.0, 26.1, 30.9], 2: [26.8, 28.6, 27.3, 29.7]}
#: psnr_f2 per sequence of every method: baselines, then seed groups (``<group>_s<seed>``)
VALUES = {
    "noisy input": [22.0, 23.5, 21.25, 24.0],
    "OIDN-fast": [29.5, 30.25, 28.0, 31.0],
    **{f"base_s{s}": v for s, v in BASE.items()},
    # better than the reference on every sequence by 2 dB or more (plus a seed-dependent wobble)
    **{f"ahead_s{s}": [x + 2.0 + 0.1 * s * (i % 2) for i, x in enumerate(v)] for s, v in BASE.items()},
    # the reference's values exactly
    **{f"same_s{s}": list(v) for s, v in BASE.items()},
}


def write_metrics(path: Path, values: dict[str, list[float]]) -> Path:
    """A denoiser-eval metrics.csv: one row per method and sequence (psnr_all = psnr_f2 - 0.25),
    and each method's ``sequence=mean`` row (with a value that must not count)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=FIELDS)
        writer.writeheader()
        for method, psnrs in values.items():
            for seq, value in zip(SEQUENCES, psnrs):
                writer.writerow({"method": method, "scene": seq.split("/")[1][:1], "sequence": seq,
                                 "frames": 6, "psnr": value, "psnr_all": value - 0.25, "psnr_f2": value})
            writer.writerow({"method": method, "scene": "mean", "sequence": "mean", "frames": 24,
                             "psnr": 99.0, "psnr_all": 99.0, "psnr_f2": 99.0})
    return path


def config(tmp_path: Path, csvs: dict[str, Path], *overrides: str):
    """conf/val_table.yaml composed, with ``evals`` replaced by ``{key: {title, csv}}``."""
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose("val_table", overrides=[f"out={tmp_path / 'val_table.md'}", "reference=base",
                                              "seeds=[0,1,2]", "labels=null", *overrides])
    cfg.evals = {key: {"title": f"{key} val", "csv": str(path)} for key, path in csvs.items()}
    return cfg


def run_table(tmp_path: Path, *overrides: str, values: dict | None = None) -> str:
    from denoiser.commands.tools.val_table import run

    csv_path = write_metrics(tmp_path / "eval" / "metrics.csv", values or VALUES)
    return run(config(tmp_path, {"one": csv_path}, *overrides)).read_text()


def table(text: str, heading: str) -> dict[str, list[str]]:
    """``{first cell: [other cells]}`` of the Markdown table under the line starting with ``heading``."""
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(heading))
    rows, seen = {}, False
    for line in lines[start + 1:]:
        if line.startswith("|"):
            seen = True
            cells = [c.strip() for c in line.strip().strip("|").split("|")]
            rows[cells[0]] = cells[1:]
        elif seen:
            break
    return rows


def seed_average(group: str, seq_index: int, values: dict = VALUES) -> float:
    """A group's value on one sequence, averaged over its seeds by a plain loop."""
    total, count = 0.0, 0
    for method, psnrs in values.items():
        if method.startswith(f"{group}_s"):
            total += psnrs[seq_index]
            count += 1
    return total / count


def test_means_and_verdicts(tmp_path):
    text = run_table(tmp_path, "candidates=[ahead,same]")
    rows = table(text, "### one val: 4 sequences")
    header = rows.pop("method")
    assert header[:2] == ["seeds", "PSNR dB frames 2+ ↑"] and header[3].startswith("vs base, ")
    assert list(rows)[1:] == ["noisy input", "OIDN-fast", "base", "ahead", "same"]  # the rule, then the rows
    # the means: per seed over sequences, then mean ± std over seeds (by hand)
    per_seed = [sum(v) / len(v) for v in BASE.values()]
    assert rows["base"][:3] == ["3", f"{statistics.mean(per_seed):.2f} ± {statistics.stdev(per_seed):.2f}",
                                f"{statistics.mean(per_seed) - 0.25:.2f} ± {statistics.stdev(per_seed):.2f}"]
    oidn = sum(VALUES["OIDN-fast"]) / 4
    assert rows["OIDN-fast"] == ["1", f"{oidn:.2f}", f"{oidn - 0.25:.2f}", "", ""]
    assert rows["noisy input"][1] == "22.69"  # (22 + 23.5 + 21.25 + 24) / 4 = 22.6875
    # the reference against itself: no interval; against OIDN-fast (better on every sequence): behind
    assert rows["base"][3] == "" and rows["base"][4].endswith(" behind")
    # 2 dB ahead on every sequence: ahead, the mean difference as computed by hand
    diffs = [seed_average("ahead", i) - seed_average("base", i) for i in range(4)]
    assert rows["ahead"][3].startswith(f"+{sum(diffs) / 4:.2f} [+2.0") and rows["ahead"][3].endswith(" ahead")
    # identical values: a zero interval, tied
    assert rows["same"][3] == "+0.00 [+0.00, +0.00] tied"


def test_a_candidate_behind_and_the_reference_first(tmp_path):
    values = {**VALUES, **{f"worse_s{s}": [x - 1.5 for x in v] for s, v in BASE.items()}}
    rows = table(run_table(tmp_path, "candidates=[worse]", values=values), "### one val")
    assert [k for k in rows if k not in ("method",) and not k.startswith("---")] == [
        "noisy input", "OIDN-fast", "base", "worse"]
    assert rows["worse"][3] == "-1.50 [-1.50, -1.50] behind"


def test_the_heading_is_the_title(tmp_path):
    assert run_table(tmp_path).startswith("# Val table: training candidates on validation splits\n")
    text = run_table(tmp_path, "title='Demo test split: the recipes, looked at once'")
    assert text.startswith("# Demo test split: the recipes, looked at once\n")


def test_every_seed_group_when_candidates_is_null(tmp_path):
    rows = table(run_table(tmp_path), "### one val")
    assert list(rows)[-3:] == ["base", "ahead", "same"]  # first-appearance order


def test_per_sequence_seed_average_matches_a_plain_loop(tmp_path):
    text = run_table(tmp_path, "candidates=[ahead,same]")
    rows = table(text, "#### one val: per sequence")
    assert rows.pop("sequence") == ["noisy input", "OIDN-fast", "base", "ahead", "same"]
    rows = {k: v for k, v in rows.items() if not k.startswith("---")}
    assert list(rows) == SEQUENCES
    for i, seq in enumerate(SEQUENCES):
        expected = [f"{VALUES['noisy input'][i]:.2f}", f"{VALUES['OIDN-fast'][i]:.2f}",
                    *(f"{seed_average(g, i):.2f}" for g in ("base", "ahead", "same"))]
        assert rows[seq] == expected, seq
    # the paired interval's mean is the mean over sequences of the seed-averaged differences
    diffs = [seed_average("base", i) - VALUES["OIDN-fast"][i] for i in range(4)]
    assert table(text, "### one val")["base"][4].startswith(f"{sum(diffs) / 4:+.2f} [")


def test_runs_of_other_seeds_are_left_out_and_named(tmp_path):
    values = {**VALUES, "base_s3": [0.0, 0.0, 0.0, 0.0]}
    text = run_table(tmp_path, "candidates=[same]", values=values)
    rows = table(text, "### one val")
    assert rows["base"][0] == "3" and rows["same"][3] == "+0.00 [+0.00, +0.00] tied"
    assert "(seeds not in [0, 1, 2]): base_s3" in text


def test_a_missing_seed_is_one_error_naming_the_csv_and_the_group(tmp_path, capsys):
    from denoiser.commands.app import guarded
    from denoiser.commands.tools.val_table import run

    values = {k: v for k, v in VALUES.items() if k != "ahead_s1"}
    good = write_metrics(tmp_path / "good" / "metrics.csv", VALUES)
    bad = write_metrics(tmp_path / "bad" / "metrics.csv", values)
    cfg = config(tmp_path, {"good": good, "bad": bad}, "candidates=[ahead]")
    lacks = re.escape(f"{bad}: candidate 'ahead' lacks seed(s) [1] of seeds=[0, 1, 2] (evaluated: [0, 2])")
    with pytest.raises(UserError, match=f"^{lacks}$"):
        run(cfg)
    with pytest.raises(SystemExit) as exc:
        guarded(run)(cfg)
    err = capsys.readouterr().err
    assert exc.value.code == 2 and err.count("\n") == 1 and str(bad) in err and "'ahead'" in err
    assert not (tmp_path / "val_table.md").exists()
    # a group absent altogether: the same kind of line
    with pytest.raises(UserError, match=f"^{re.escape(str(good))}: no runs of candidate 'nope'"):
        run(config(tmp_path, {"good": good}, "candidates=[nope]"))


def test_two_runs_of_one_split_read_as_one(tmp_path):
    """``csv: [a, b]``: candidates from two evaluation runs of the same split, paired as if one run
    had evaluated them all; the baselines both runs hold are taken once."""
    from denoiser.commands.tools.val_table import run

    baselines = {k: VALUES[k] for k in ("noisy input", "OIDN-fast")}
    first = write_metrics(tmp_path / "a" / "metrics.csv", {**baselines, **{f"base_s{s}": v for s, v in BASE.items()}})
    ahead = {k: v for k, v in VALUES.items() if k.startswith("ahead_s")}
    second = write_metrics(tmp_path / "b" / "metrics.csv", {**baselines, **ahead})
    cfg = config(tmp_path, {"one": first}, "candidates=[ahead]")
    cfg.evals.one.csv = [str(first), str(second)]
    two = run(cfg).read_text()
    one = run_table(tmp_path / "single", "candidates=[ahead]", values={**baselines, **VALUES})
    assert table(two, "### one val: 4 sequences") == table(one, "### one val: 4 sequences")
    assert f"From `{first}` and `{second}`." in two and two.count("SHA-256") == 2
    # a baseline that differs between the runs: they did not see the same frames
    other = dict(baselines, **{"OIDN-fast": [x + 0.5 for x in VALUES["OIDN-fast"]]})
    write_metrics(tmp_path / "b" / "metrics.csv", {**other, **ahead})
    with pytest.raises(UserError, match=r"b/metrics\.csv: method 'OIDN-fast' differs from .*a/metrics\.csv on val/a_000"):
        run(cfg)


def test_prefix_pairs_two_runs_of_the_same_labels(tmp_path):
    """``prefix``: two runs that label their students alike (make demo's before and after) are paired
    on the same split; the baselines keep their names and are checked equal."""
    from denoiser.commands.tools.val_table import run

    baselines = {k: VALUES[k] for k in ("noisy input", "OIDN-fast")}
    before = write_metrics(tmp_path / "a" / "metrics.csv", {**baselines, **{f"s_s{s}": v for s, v in BASE.items()}})
    after = write_metrics(tmp_path / "b" / "metrics.csv",
                          {**baselines, **{f"s_s{s}": [x + 1.0 for x in v] for s, v in BASE.items()}})
    cfg = config(tmp_path, {"one": before}, "reference=prev_s", "candidates=[s]")
    cfg.evals = {"one": {"title": "one val", "csv": [str(before), str(after)], "prefix": ["prev_", ""]}}
    rows = table(run(cfg).read_text(), "### one val: 4 sequences")
    assert list(rows)[2:] == ["noisy input", "OIDN-fast", "prev_s", "s"]
    assert rows["s"][3] == "+1.00 [+1.00, +1.00] ahead"   # every sequence 1 dB above, after minus before
    cfg.evals = {"one": {"title": "one val", "csv": [str(before), str(after)], "prefix": [""]}}
    with pytest.raises(Exception, match="1 prefixes for 2 csv files"):
        run(cfg)
