"""The generated results report: its statistics against hand-computed values, stale sections, and
the committed documents equal to what their data generate."""

from __future__ import annotations

from pathlib import Path

import pytest

from dva.analysis import report
from dva.runner import runtime

ROOT = Path(__file__).resolve().parents[1]

CURVE = """iteration,env_steps,wall_time,eval_return,actor_grad_norm
0,0,0.0,100,
1,256,30.0,,5.0
2,512,60.0,700,9.0
3,768,120.0,,2.0
4,1024,180.0,500,3.0
"""


def make_root(tmp_path: Path, fingerprint: str = "") -> report.Layout:
    """A repository with one source file, one section of two seeds and a document."""
    (tmp_path / "src").mkdir()
    (tmp_path / "src" / "task.py").write_text("reward = 1\n")
    folder = tmp_path / report.RESULTS / "toy"
    folder.mkdir(parents=True)
    (folder / "s0.csv").write_text(CURVE)
    (folder / "s1.csv").write_text(CURVE.replace("700", "900").replace(",500,", ",300,"))
    (folder / "section.toml").write_text(
        'command = "dva train --task toy"\nmachine = "a CPU"\ncommit = "0123abc"\n'
        f'sources = ["src/task.py"]\nconfigs = []\nfingerprint = "{fingerprint}"\n\n'
        '[runs]\n"D.Va" = ["s0.csv", "s1.csv"]\n\n'
        '[[tables]]\ncolumns = ["untrained", "first 600", "final", "median10", "best", "env steps", "grad norm", '
        '"at 3 it", "median10 interval"]\n'
    )
    (tmp_path / report.RESULTS / "summary.toml").write_text(
        '[[status]]\ntask = "toy"\n"D.Va" = "final {{toy|D.Va|final}}, 2× at {{toy|D.Va|minutes to 600}} min"\n'
    )
    for document in report.DOCUMENTS:
        path = tmp_path / document
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(
            "# Doc\n\n<!-- generated: status -->\n<!-- end -->\n\n<!-- generated: toy -->\nold\n<!-- end -->\n"
        )
    return report.Layout(tmp_path)


def test_run_statistics_are_the_hand_computed_ones(tmp_path):
    root = make_root(tmp_path)
    text = report.generate(root, "docs/results.md")
    # Seed 0 evaluates 100, 700, 500; seed 1 100, 900, 300. Final: mean 400, sample std
    # 100·√2 = 141; median of the (three) last: 500 and 300; both first pass 600 at the 60-second
    # evaluation (512 steps).
    assert "| D.Va | 100 / 100 | 1.0 min (1k steps) / 1.0 min (1k steps) | 400 ± 141 | 400 ± 141 | 700 / 900 |" in text
    # At iteration 3 neither evaluated: the next evaluation, iteration 4's, counts. Resampling the
    # two medians gives means 300, 400, 500 with chances ¼, ½, ¼: the 95 % interval is [300, 500].
    assert "| 1k / 1k | 9 / 9 | 500 / 300 | [300, 500] |" in text
    assert report.interval([500.0]) == "–"  # one seed has no interval
    assert "| toy | final 400 ± 141†, 2× at 1.0 / 1.0† min |" in text  # a stale section's values are marked
    assert "old" not in text


def test_a_section_is_stale_exactly_when_its_sources_changed(tmp_path):
    root = make_root(tmp_path)
    assert "**Stale**" in report.generate(root, "docs/results.md")
    report.stamp(root, "toy", "4567def")
    fresh = report.generate(root, "docs/results.md")
    assert "**Stale**" not in fresh and "†" not in fresh and "code `4567def`" in fresh
    (root.root / "src" / "task.py").write_text("reward = 2\n")
    assert "**Stale**" in report.generate(root, "docs/results.md")


def test_a_setting_measured_apart_is_stale_on_its_own(tmp_path):
    root = make_root(tmp_path)  # the section's fingerprint "" is stale
    toml = root.folder / "toy" / "section.toml"
    toml.write_text(
        toml.read_text().replace('"D.Va" = ["s0.csv", "s1.csv"]', '"D.Va" = ["s0.csv", "s1.csv"]\n"DrQ" = ["s1.csv"]')
        + '\n[settings."D.Va"]\ncommit = "89abcde"\nconfigs = []\nfingerprint = ""\n'
    )
    with pytest.raises(report.DvaUsageError, match=r'a table \[settings."DrQ"\]'):
        report.stamp(root, "toy", "89abcde", "DrQ")
    report.stamp(root, "toy", "89abcde", "D.Va")  # D.Va re-measured: only DrQ's row is stale
    text = report.generate(root, "docs/results.md")
    assert "**Stale rows** (†)" in text and "**Stale**:" not in text
    assert "code `0123abc`; D.Va: `89abcde`" in text
    assert "| D.Va | 100 / 100 |" in text and "| DrQ† | 100 |" in text
    assert "| toy | final 400 ± 141, 2× at 1.0 / 1.0 min |" in text  # its placeholders unmarked
    assert 'commit = "0123abc"' in toml.read_text()  # the section's own stamp untouched
    report.stamp(root, "toy", "4567def")  # the rest re-measured: nothing stale
    text = report.generate(root, "docs/results.md")
    assert "Stale" not in text and "†" not in text and "code `4567def`; D.Va: `89abcde`" in text
    (root.root / "src" / "task.py").write_text("reward = 2\n")  # the code both measure changed
    text = report.generate(root, "docs/results.md")
    assert "**Stale**:" in text and "| toy | final 400 ± 141†" in text
    toml.write_text(toml.read_text() + '\n[settings."DrQ"]\ncommit = "fedcba9"\nconfigs = []\nfingerprint = ""\n')
    # Every row stamped apart: the section's own commit measures none of them and is not shown.
    assert "code D.Va: `89abcde`; DrQ: `fedcba9`;" in report.generate(root, "docs/results.md")


def test_write_then_check_agree(tmp_path):
    root = make_root(tmp_path)
    assert report.differences(root) != ""
    report.write(root)
    assert report.differences(root) == ""


def test_bad_columns_and_thinned_logs_are_refused(tmp_path):
    root = make_root(tmp_path)
    with pytest.raises(ValueError, match="unknown results column 'fastest'"):
        report.run_column("fastest")
    folder = root.folder / "toy"
    (folder / "s0.csv").write_text(CURVE.replace("1,256,30.0,,5.0\n", ""))
    with pytest.raises(ValueError, match="logs actor_grad_norm for 3 of its 4 iterations"):
        report.generate(root, "docs/results.md")
    with pytest.raises(ValueError, match="no setting 'DrQ-v2'"):
        report.placeholder(root, "toy|DrQ-v2|final")


def test_the_documents_equal_what_their_data_generate():
    """Run `dva report` after changing data, a section.toml, or the code a section measures."""
    diff = report.differences(report.Layout(ROOT))
    assert diff == "", "the results documents differ from their data; run `dva report`:\n" + diff


def test_every_data_folder_is_a_section_the_documents_show():
    folders = {path.name for path in (ROOT / report.RESULTS).iterdir() if path.is_dir()}
    sections = {path.parent.name for path in (ROOT / report.RESULTS).glob("*/section.toml")}
    assert folders == sections
    shown = "".join((ROOT / document).read_text() for document in report.DOCUMENTS)
    assert not [name for name in sections if f"<!-- generated: {name} -->" not in shown]


def test_a_published_curve_is_read_from_its_columns_and_drawn(tmp_path):
    root = make_root(tmp_path)
    folder = root.folder / "toy"
    (folder / "published.csv").write_text("frames,seed_1,seed_2,seed_3\n0,1,2,3\n1000,400,100,700\n")
    toml = (folder / "section.toml").read_text()
    (folder / "section.toml").write_text(toml.replace("[runs]", "plot = true\n[runs]"))
    section = report.Section.load(root, "toy")
    assert section.published_curve() is None
    plain = {path.name: path.read_bytes() for path in section.plot()}
    (folder / "section.toml").write_text(
        toml.replace(
            "[runs]",
            'plot = true\npublished = {csv = "published.csv", x = "frames", columns = ["seed_1", "seed_2", "seed_3"], '
            'label = "as published"}\n[runs]',
        )
    )
    curve = report.Section.load(root, "toy").published_curve()
    assert curve.label == "as published"
    assert curve.env_steps.tolist() == [0, 1000]
    assert curve.values.tolist() == [[1, 2, 3], [400, 100, 700]]
    drawn = {path.name: path.read_bytes() for path in report.Section.load(root, "toy").plot()}
    # Beside the runs against env steps only: the plot against wall-clock is unchanged.
    assert drawn["eval_return_vs_env_steps.png"] != plain["eval_return_vs_env_steps.png"]
    assert drawn["eval_return_vs_wall_time.png"] == plain["eval_return_vs_wall_time.png"]
    bad = 'published = {csv = "published.csv", x = "step", columns = ["seed_1"], label = "x"}\n[runs]'
    bad = toml.replace("[runs]", bad)
    (folder / "section.toml").write_text(bad)
    with pytest.raises(ValueError, match="no column 'step'"):
        report.Section.load(root, "toy").published_curve()


def test_a_report_of_a_users_own_folder_of_sections(tmp_path, capsys):
    """`dva report --sections DIR --documents FILE`: a user's own runs, one section each, fill the
    generated blocks of their own document (no summary file needed), and the check then passes."""
    from dva.cli import main

    folder = tmp_path / "my_results" / "sweep"
    folder.mkdir(parents=True)
    (folder / "lr_1e-3.csv").write_text(CURVE)
    (folder / "section.toml").write_text(
        'command = "dva train --task hopper --shac.actor-lr 1e-3"\nmachine = "my laptop"\ncommit = "abc1234"\n'
        'fingerprint = ""\n\n[runs]\n"lr 1e-3" = ["lr_1e-3.csv"]\n\n[[tables]]\ncolumns = ["final", "best"]\n'
    )
    (tmp_path / "report.md").write_text("# Mine\n\n<!-- generated: sweep -->\n<!-- end -->\n")
    options = ["--root", str(tmp_path), "--sections", "my_results", "--documents", "report.md"]
    main(["report", *options])
    text = (tmp_path / "report.md").read_text()
    assert "| lr 1e-3 | 500 | 700 |" in text and "data in `my_results/sweep/`" in text
    with pytest.raises(SystemExit) as exit_info:
        main(["report", "--check", *options])
    assert exit_info.value.code == 0 and "agree with their data" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        main(["report", "--root", str(tmp_path), "--sections", "nowhere"])
    assert "--sections nowhere is not a folder" in capsys.readouterr().err


def test_training_episode_returns_are_read_at_an_iteration(tmp_path):
    """``train at N it``: the training episodes' return logged at iteration N (the latest that ended
    by then); "–" before any ended or past the run's end."""
    curve = (
        "iteration,env_steps,wall_time,train_return,eval_return\n"
        "0,0,0,nan,100\n1,8,1,nan,\n2,16,2,50,\n3,24,3,,\n4,32,4,80,500\n"
    )
    (tmp_path / "s0.csv").write_text(curve)
    (tmp_path / "s1.csv").write_text(curve.replace(",50,", ",60,"))
    runs = [report.Run.load(tmp_path / name) for name in ("s0.csv", "s1.csv")]
    cells = {n: report.run_column(f"train at {n} it")[1](runs) for n in (1, 3, 4, 6)}
    assert cells == {1: "– / –", 3: "50 / 60", 4: "80 / 80", 6: "– / –"}
    assert report.run_column("train at 3 it")[0] == "training episodes at iteration 3"


def test_the_machine_column_names_each_runs_cpu_from_its_kept_machines_file(tmp_path):
    """``machine``: the CPU model of each start or resume (``NAME.machines.txt`` beside the CSV),
    the accelerator when it is not the CPU, and how many runs ran where when they differ."""
    for name in ("s0", "s1", "s2"):
        (tmp_path / f"{name}.csv").write_text(CURVE)
    zen = "x86_64 2 cores (AMD EPYC, family 26 model 2), JAX 0.10.2 on cpu (cpu)"
    (tmp_path / "s0.machines.txt").write_text(f"iteration 0: {zen}\niteration 3: {zen}\n")
    (tmp_path / "s1.machines.txt").write_text(
        f"iteration 0: {zen}\niteration 2: x86_64 16 cores (Intel Xeon, family 6 model 143), JAX 0.10.2 on gpu (H100)\n"
    )
    runs = [report.Run.load(tmp_path / f"s{seed}.csv") for seed in range(3)]
    column = report.run_column("machine")[1]
    assert column(runs[:1]) == "AMD EPYC, family 26 model 2"  # a resume on the same CPU is one machine
    assert column(runs) == (
        "AMD EPYC, family 26 model 2 (1 of 3); AMD EPYC, family 26 model 2 then Intel Xeon, family 6 model 143 + H100 "
        "(1 of 3); not recorded (1 of 3)"
    )
    # The line the runner writes (this machine's) reads back as this machine's CPU model.
    (tmp_path / "s2.machines.txt").write_text(runtime.machine_line(0) + "\n")
    assert report.Run.load(tmp_path / "s2.csv").machines == (runtime.cpu_model(),)
    (tmp_path / "s2.machines.txt").write_text("a laptop\n")
    with pytest.raises(report.DvaUsageError, match="not a machines.txt line"):
        report.Run.load(tmp_path / "s2.csv")
