"""The results report (``dva report``): every table of a set of markdown documents generated from the
data kept in a folder of sections, so no number can drift from its data. This repository's is
``docs/results/`` with ``docs/results.md``, ``README.md`` and ``docs/index.md`` (the defaults); a
user's own runs make one the same way (``dva report --sections my_results --documents report.md``).

Each section's folder holds its data (CSV files) and a ``section.toml`` that says how they were
made and what to show::

    command = "dva compare fig4 --tasks hopper --seeds 0 1 --minutes 30 --workers 2"
    machine = "2-core x86_64 CPU, one core per run"
    commit = "0123abc"                      # the code that made the data
    sources = ["src/dva/tasks/legged.py"]   # the code it measures ...
    configs = [["hopper", "dva", "cpu"]]    # ... and the configs (task, algo, preset)
    fingerprint = "…"                       # their hash when measured (`dva report --stamp`)
    plot = true                             # draw the runs' curves (return vs env steps and time)
    published = {csv = "published.csv", x = "frames", columns = ["lowest", "median", "highest"], label = "…"}
                                            # the authors' curve beside them (their seeds' median and range)

    [runs]                                  # setting → its runs' CSV files, one per seed
    "D.Va" = ["hopper_dva_s0.csv", "hopper_dva_s1.csv"]
                                            # (a run's machines.txt kept beside its CSV as
                                            # hopper_dva_s0.machines.txt feeds the "machine" column)

    [[tables]]                              # a table of the runs: one column per statistic
    columns = ["untrained", "first 3000", "final", "median10", "best", "env steps"]

    [[tables]]                              # or a benchmark's own CSV, one row per CSV row
    csv = "throughput.csv"
    columns = [["task", "task"], ["forward (s)", "forward_s:.3f"]]

    [settings."D.Va"]                       # a setting measured apart from the rest (optional):
    commit = "4567def"                      # its own code, configs and fingerprint
    configs = [["hopper", "dva", "cpu"]]    # (`dva report --stamp NAME --setting "D.Va"`)
    fingerprint = "…"

The documents mark each place with HTML comments, ``<!-- generated: NAME -->`` …
``<!-- end -->`` (NAME a section folder, or a key of ``summary.toml``), which the generator fills. Summary rows
(``docs/results/summary.toml``) are text with ``{{section|setting|column}}`` and
``{{section/file.csv|key=value|field:format}}`` placeholders. When the hash of a section's sources
and configs no longer matches its fingerprint, the section is marked stale; a setting stamped apart
is judged by its own, so a section re-measured one setting at a time marks only the rows still stale.
"""

from __future__ import annotations

import csv
import dataclasses
import difflib
import functools
import hashlib
import json
import re
import tomllib
from collections.abc import Callable
from pathlib import Path

import numpy as np

from dva.algorithms import make_config
from dva.analysis.bench import markdown_table
from dva.analysis.plots import LATE_POINTS, PublishedCurve, plot_curves
from dva.analysis.statistics import bootstrap_interval, interval_text, mean_and_std_text, sample_std, whole
from dva.errors import DvaUsageError
from dva.runner.runtime import machine_in_line

RESULTS = Path("docs/results")
DOCUMENTS = ("docs/results.md", "README.md", "docs/index.md")


@dataclasses.dataclass(frozen=True)
class Layout:
    """Where a report lives: its ``root`` (which sections' ``sources`` are relative to), its folder
    of ``sections`` and the ``documents`` whose generated blocks it fills (both relative to root).
    An optional ``summary.toml`` in the sections folder holds the summary rows."""

    root: Path = Path(".")
    sections: Path = RESULTS
    documents: tuple[str, ...] = DOCUMENTS

    @property
    def folder(self) -> Path:
        return self.root / self.sections

    def summary(self) -> dict:
        path = self.folder / "summary.toml"
        return tomllib.loads(path.read_text()) if path.exists() else {}


BLOCK = re.compile(r"(<!-- generated: (?P<name>[\w-]+) -->\n)(?P<body>.*?)(<!-- end -->)", re.S)
PLACEHOLDER = re.compile(r"\{\{(.+?)\}\}")
STALE_MARK = "†"


@dataclasses.dataclass
class Run:
    """One run's evaluations (iteration, wall-clock in seconds, env steps, return) and what else it
    logged."""

    name: str
    iteration: np.ndarray
    wall_time: np.ndarray
    env_steps: np.ndarray
    eval_return: np.ndarray
    iterations: int
    grad_norms: np.ndarray
    iteration_times: np.ndarray
    # The training episodes' return as logged each iteration (the latest that ended), and when.
    train_iteration: np.ndarray
    train_return: np.ndarray
    # The machines it trained on, in order (from the machines.txt kept beside its CSV); () if none kept.
    machines: tuple[str, ...] = ()

    @classmethod
    def load(cls, path: Path) -> Run:
        rows = csv_rows(path)
        evals = [r for r in rows if r.get("eval_return") not in (None, "", "nan")]
        if not evals:
            raise DvaUsageError(f"{path} has no evaluations")

        def logged(key: str) -> np.ndarray:
            return np.array([float(r[key]) for r in rows if r.get(key) not in (None, "", "nan")])

        trained = [r for r in rows if r.get("train_return") not in (None, "", "nan")]

        return cls(
            path.name,
            np.array([int(float(r["iteration"])) for r in evals]),
            np.array([float(r["wall_time"]) for r in evals]),
            np.array([float(r["env_steps"]) for r in evals]),
            np.array([float(r["eval_return"]) for r in evals]),
            int(float(rows[-1]["iteration"])),
            logged("actor_grad_norm"),
            logged("iteration_time"),
            np.array([int(float(r["iteration"])) for r in trained]),
            np.array([float(r["train_return"]) for r in trained]),
            run_machines(path),
        )

    def first(self, threshold: float) -> int | None:
        """The index of the first evaluation at or above ``threshold``."""
        reached = np.flatnonzero(self.eval_return >= threshold)
        return int(reached[0]) if len(reached) else None

    def at(self, axis: np.ndarray, value: float) -> float | None:
        """The first evaluation at or after ``value`` on ``axis`` (iteration, wall-clock or env steps)."""
        index = np.flatnonzero(axis >= value)
        return float(self.eval_return[index[0]]) if len(index) else None


def steps(value: float) -> str:
    """Env steps as 83k, 1.33M."""
    return f"{value / 1e6:.2f}M" if value >= 1e6 else f"{value / 1e3:.0f}k"


def spread(values: list[float]) -> str:
    """One seed's value, or the mean ± the sample std over seeds."""
    return mean_and_std_text(float(np.mean(values)), sample_std(values), len(values))


def interval(values: list[float]) -> str:
    """The bootstrap 95 % interval of the mean over seeds, as "[low, high]"; "–" for one seed."""
    return interval_text(*bootstrap_interval(values), len(values))


def per_seed(values: list[str]) -> str:
    return " / ".join(values)


def first_column(threshold: float, with_steps: bool = True) -> Callable[[list[Run]], str]:
    """When each seed's evaluations first reached ``threshold``: minutes (and env steps), or "never"."""

    def when(run: Run) -> str:
        index = run.first(threshold)
        if index is None:
            return "never"
        minutes = f"{run.wall_time[index] / 60:.1f}"
        return f"{minutes} min ({steps(run.env_steps[index])} steps)" if with_steps else minutes

    return lambda runs: per_seed([when(run) for run in runs])


def at_column(axis: str, value: float) -> Callable[[list[Run]], str]:
    """Each seed's evaluation at ``value`` on ``axis`` ("iteration", "wall_time" in seconds or
    "env_steps")."""

    def cell(runs: list[Run]) -> str:
        values = [run.at(getattr(run, axis), value) for run in runs]
        return per_seed(["–" if v is None else whole(v) for v in values])

    return cell


def train_at_column(iteration: int) -> Callable[[list[Run]], str]:
    """Each seed's training-episode return as logged at ``iteration`` (the episodes that ended last
    by then, acting as training acts)."""

    def cell(runs: list[Run]) -> str:
        values = [run.train_return[run.train_iteration <= iteration] for run in runs]
        reached = [run.iterations >= iteration for run in runs]
        return per_seed([whole(v[-1]) if ok and len(v) else "–" for v, ok in zip(values, reached)])

    return cell


def run_machines(path: Path) -> tuple[str, ...]:
    """The machines a run trained on, from its ``machines.txt`` kept beside its CSV as
    ``NAME.machines.txt``: each start's or resume's CPU model (and its accelerator, if not the CPU),
    in order, repeats merged; () when none is kept."""
    kept = path.with_name(f"{path.stem}.machines.txt")
    if not kept.is_file():
        return ()
    machines: list[str] = []
    for line in kept.read_text().splitlines():
        if (machine := machine_in_line(line)) is None:
            raise DvaUsageError(f"{kept}: {line!r} is not a machines.txt line (iteration N: <machine>)")
        if not machines or machines[-1] != machine:
            machines.append(machine)
    return tuple(machines)


def machine_cell(runs: list[Run]) -> str:
    """The machines of a setting's runs: one if all ran on it, else each with its number of runs."""
    names = [" then ".join(run.machines) or "not recorded" for run in runs]
    distinct = list(dict.fromkeys(names))
    if len(distinct) == 1:
        return distinct[0]
    return "; ".join(f"{name} ({names.count(name)} of {len(runs)})" for name in distinct)


def max_grad_norm(runs: list[Run]) -> str:
    """The largest logged actor gradient norm of each run: only where every iteration was logged."""
    for run in runs:
        if len(run.grad_norms) < run.iterations:
            raise DvaUsageError(
                f"{run.name} logs actor_grad_norm for {len(run.grad_norms)} of its {run.iterations} iterations: "
                "its largest is not the run's"
            )
    return per_seed([f"{run.grad_norms.max():.0f}" for run in runs])


FIXED_COLUMNS: dict[str, tuple[str, Callable[[list[Run]], str]]] = {
    "seeds": ("seeds", lambda runs: str(len(runs))),
    "untrained": ("untrained", lambda runs: per_seed([whole(r.eval_return[0]) for r in runs])),
    "final": ("final", lambda runs: spread([r.eval_return[-1] for r in runs])),
    "median10": (
        f"median of the last {LATE_POINTS}",
        lambda runs: spread([np.median(r.eval_return[-LATE_POINTS:]) for r in runs]),
    ),
    "median10 interval": (
        "its 95 % interval (bootstrap over seeds)",
        lambda runs: interval([np.median(r.eval_return[-LATE_POINTS:]) for r in runs]),
    ),
    "best": ("best", lambda runs: per_seed([whole(r.eval_return.max()) for r in runs])),
    "env steps": ("env steps", lambda runs: per_seed([steps(r.env_steps[-1]) for r in runs])),
    "minutes": ("minutes", lambda runs: per_seed([f"{r.wall_time[-1] / 60:.1f}" for r in runs])),
    "iterations": ("iterations", lambda runs: per_seed([str(r.iterations) for r in runs])),
    "s/iteration": (
        "s / iteration",
        lambda runs: per_seed([f"{r.wall_time[-1] / max(r.iterations, 1):.2f}" for r in runs]),
    ),
    "grad norm": ("largest pre-clip actor gradient norm", max_grad_norm),
    "machine": ("machine", machine_cell),
    "iteration time": (
        "median s / iteration",
        lambda runs: per_seed([f"{np.median(r.iteration_times):.2f}" for r in runs]),
    ),
}


def run_column(spec: str) -> tuple[str, Callable[[list[Run]], str]]:
    """A column of a runs table from its name: one of :data:`FIXED_COLUMNS`, ``first T`` (when each
    seed's evaluations first reached T), ``at M min``, ``at Nk steps`` or ``at N it`` (the
    evaluation then), ``train at N it`` (the training episodes' return logged then)."""
    if spec in FIXED_COLUMNS:
        return FIXED_COLUMNS[spec]
    if match := re.fullmatch(r"first (-?[\d.]+)", spec):
        return f"first ≥ {match[1]}", first_column(float(match[1]))
    if match := re.fullmatch(r"minutes to (-?[\d.]+)", spec):
        return f"minutes to {match[1]}", first_column(float(match[1]), with_steps=False)
    if match := re.fullmatch(r"at ([\d.]+) min", spec):
        return f"eval at {match[1]} min", at_column("wall_time", 60 * float(match[1]))
    if match := re.fullmatch(r"at ([\d.]+)k steps", spec):
        return f"eval at {match[1]}k env steps", at_column("env_steps", 1e3 * float(match[1]))
    if match := re.fullmatch(r"at (\d+) it", spec):
        return f"eval at iteration {match[1]}", at_column("iteration", float(match[1]))
    if match := re.fullmatch(r"train at (\d+) it", spec):
        return f"training episodes at iteration {match[1]}", train_at_column(int(match[1]))
    allowed = ", ".join(
        [*FIXED_COLUMNS, "first T", "minutes to T", "at M min", "at Nk steps", "at N it", "train at N it"]
    )
    raise DvaUsageError(f"unknown results column {spec!r}; allowed: {allowed}")


def csv_rows(path: Path) -> list[dict[str, str]]:
    if not path.is_file():
        raise DvaUsageError(f"the results data {path} does not exist")
    status = path.stat()
    return list(_parsed_csv(path.resolve(), status.st_mtime_ns, status.st_size))


@functools.lru_cache(maxsize=4096)
def _parsed_csv(path: Path, mtime_ns: int, size: int) -> tuple[dict[str, str], ...]:
    """A CSV's rows, parsed once per version of the file (a report reads each file many times)."""
    with path.open() as f:
        return tuple(csv.DictReader(f))


def csv_field(row: dict[str, str], spec: str) -> str:
    """``field`` or ``field:format`` of one CSV row (numbers formatted as floats)."""
    field, _, form = spec.partition(":")
    if field not in row:
        raise DvaUsageError(f"no column {field!r} in the CSV; it has: {', '.join(row)}")
    return format(float(row[field]), form) if form else row[field]


@dataclasses.dataclass
class Section:
    """A results folder with its ``section.toml``."""

    name: str
    folder: Path
    meta: dict
    shown: Path  # the folder as the documents name it (relative to the root)

    @classmethod
    def load(cls, layout: Layout, name: str) -> Section:
        folder = layout.folder / name
        path = folder / "section.toml"
        if not path.exists():
            raise DvaUsageError(f"no results section {name!r}: {path.relative_to(layout.root)} does not exist")
        return cls(name, folder, tomllib.loads(path.read_text()), layout.sections / name)

    def runs(self, setting: str) -> list[Run]:
        settings = self.meta.get("runs", {})
        if setting not in settings:
            raise DvaUsageError(f"section {self.name}: no setting {setting!r}; it has: {', '.join(settings)}")
        return [Run.load(self.folder / file) for file in settings[setting]]

    def stamp_of(self, setting: str | None = None) -> dict:
        """What says how ``setting`` was measured: its own ``[settings.…]`` table where it was
        measured apart from the rest, else the section's (commit, configs, fingerprint)."""
        return self.meta.get("settings", {}).get(setting, self.meta)

    def fingerprint(self, layout: Layout, setting: str | None = None) -> str:
        """The hash of the code and configs the section (or ``setting``) measures, as they are now."""
        digest = hashlib.sha256()
        for source in sorted(self.meta.get("sources", [])):
            digest.update(source.encode() + (layout.root / source).read_bytes())
        for task, algo, preset in self.stamp_of(setting).get("configs", []):
            digest.update(_config_json(task, algo, preset))
        return digest.hexdigest()[:16]

    def is_stale(self, layout: Layout, setting: str | None = None) -> bool:
        return self.stamp_of(setting).get("fingerprint") != self.fingerprint(layout, setting)

    def staleness(self, layout: Layout) -> tuple[bool, set[str]]:
        """Whether the whole section is stale, and else which of its settings are (where some were
        stamped apart: each judged by its own stamp, the rest by the section's)."""
        settings = set(self.meta.get("runs", {}))
        if "settings" not in self.meta or not settings:
            return self.is_stale(layout), set()
        stale = {setting for setting in settings if self.is_stale(layout, setting)}
        return (True, set()) if stale == settings else (False, stale)

    def tables(self, stale_rows: set[str]) -> list[str]:
        """The section's tables, the rows of ``stale_rows`` marked."""
        tables = []
        for table in self.meta.get("tables", []):
            if "csv" in table:
                records = csv_rows(self.folder / table["csv"])
                header = [name for name, _ in table["columns"]]
                cells = [[csv_field(r, spec) for _, spec in table["columns"]] for r in records]
                tables.append(markdown_table(header, cells) + "\n")
                continue
            columns = [run_column(spec) for spec in table["columns"]]
            settings = table.get("settings", list(self.meta.get("runs", {})))
            rows = [
                [setting + STALE_MARK * (setting in stale_rows)] + [cell(self.runs(setting)) for _, cell in columns]
                for setting in settings
            ]
            tables.append(markdown_table([table.get("first", "setting")] + [h for h, _ in columns], rows) + "\n")
        return tables

    def block(self, layout: Layout) -> str:
        """The generated part of the section: how it was made, stale or not, and its tables."""
        meta = self.meta
        apart = meta.get("settings", {})
        # Where every row was stamped apart, the section's own commit measures none of them.
        every_setting_apart = bool(apart) and set(meta.get("runs", {})) <= set(apart)
        code = "; ".join(
            [commit_text(meta["commit"])] * (not every_setting_apart)
            + [f"{name}: {commit_text(stamp['commit'])}" for name, stamp in apart.items()]
        )
        lines = [
            f"Command: `{meta['command']}`  ",
            f"Machine: {meta['machine']}; code {code}; data in `{self.shown.as_posix()}/`.",
        ]
        all_stale, stale_rows = self.staleness(layout)
        if stale_rows:
            lines.append(
                f"\n**Stale rows** ({STALE_MARK}): the code or configuration they measure has changed since "
                "they were measured; re-run them to bring them up to date."
            )
        elif all_stale:
            lines.append(
                "\n**Stale**: the code or configuration this measures has changed since it was "
                "measured; re-run the command to bring it up to date."
            )
        return "\n".join(lines) + "\n" + "".join("\n" + table for table in self.tables(stale_rows))

    def plot(self) -> list[Path]:
        curves = {
            setting: [
                {"eval_return": run.eval_return, "env_steps": run.env_steps, "wall_time": run.wall_time}
                for run in self.runs(setting)
            ]
            for setting in self.meta.get("runs", {})
        }
        return plot_curves(curves, self.folder, "eval_return", self.published_curve())

    def published_curve(self) -> PublishedCurve | None:
        """The authors' curve that ``published`` names (its x column and its seeds' columns), if any."""
        if "published" not in self.meta:
            return None
        spec = self.meta["published"]
        rows = csv_rows(self.folder / spec["csv"])
        return PublishedCurve(
            spec["label"],
            np.array([float(csv_field(row, spec["x"])) for row in rows]),
            np.array([[float(csv_field(row, column)) for column in spec["columns"]] for row in rows]),
        )


def commit_text(commit: str) -> str:
    """A commit hash in code style; free text (several commits explained) as it is."""
    return f"`{commit}`" if re.fullmatch(r"[0-9a-f]{7,40}", commit) else commit


@functools.cache
def _config_json(task: str, algo: str, preset: str) -> bytes:
    """A config as the fingerprint hashes it (the presets are constants of the code)."""
    return json.dumps(dataclasses.asdict(make_config(task, algo, preset)), sort_keys=True, default=str).encode()


def placeholder(layout: Layout, text: str) -> str:
    """The value of one ``{{…}}``: ``section|setting|column`` or ``section/file.csv|key=value|field:format``."""
    parts = [part.strip() for part in text.split("|")]
    if len(parts) != 3:
        raise DvaUsageError(f"placeholder {{{{{text}}}}} must have three parts separated by '|'")
    where, pick, what = parts
    if where.endswith(".csv"):
        key, _, value = pick.partition("=")
        rows = [r for r in csv_rows(layout.folder / where) if r.get(key) == value]
        if len(rows) != 1:
            raise DvaUsageError(f"placeholder {{{{{text}}}}}: {len(rows)} rows of {where} have {key} = {value!r}")
        section = Section.load(layout, where.split("/")[0])
        return csv_field(rows[0], what) + STALE_MARK * section.is_stale(layout)
    section = Section.load(layout, where)
    return run_column(what)[1](section.runs(pick)) + STALE_MARK * section.is_stale(layout, pick)


def fill(layout: Layout, text: str) -> str:
    return PLACEHOLDER.sub(lambda match: placeholder(layout, match[1]), text)


def summary_block(layout: Layout, rows: list[dict]) -> str:
    header = list(rows[0])
    table = markdown_table(header, [[fill(layout, row[key]) for key in header] for row in rows]) + "\n"
    if STALE_MARK in table:
        table += f"\n{STALE_MARK} from a section whose code has changed since it was measured (marked stale there).\n"
    return table


def generate(layout: Layout, path: str) -> str:
    """The document at ``path`` with every generated block filled from the data."""
    summary = layout.summary()
    text = (layout.root / path).read_text()

    def body(match: re.Match) -> str:
        name = match["name"]
        if isinstance(summary.get(name), str):  # a paragraph
            content = fill(layout, summary[name].strip()) + "\n"
        elif name in summary:
            content = summary_block(layout, summary[name])
        else:
            content = Section.load(layout, name).block(layout)
        return match[1] + "\n" + content + "\n" + match[4]

    return BLOCK.sub(body, text)


def differences(layout: Layout) -> str:
    """A unified diff of every document against its regenerated self ('' when all agree)."""
    diff: list[str] = []
    for path in layout.documents:
        old, new = (layout.root / path).read_text(), generate(layout, path)
        diff += difflib.unified_diff(old.splitlines(True), new.splitlines(True), path, f"{path} (regenerated)")
    return "".join(diff)


def write(layout: Layout, plots: bool = False) -> list[Path]:
    """Regenerate every document (and with ``plots`` every section's curves); returns what changed."""
    written = []
    for path in layout.documents:
        new = generate(layout, path)
        if new != (layout.root / path).read_text():
            (layout.root / path).write_text(new)
            written.append(layout.root / path)
    if plots:
        for folder in sorted(layout.folder.glob("*/section.toml")):
            section = Section.load(layout, folder.parent.name)
            if section.meta.get("plot"):
                written += section.plot()
    return written


def stamp(layout: Layout, name: str, commit: str, setting: str | None = None) -> None:
    """Record that section ``name``'s data (or only ``setting``'s, in its ``[settings."…"]`` table)
    was just measured with the code at ``commit``."""
    section = Section.load(layout, name)
    path = section.folder / "section.toml"
    text = path.read_text()
    # the part of the file that holds the stamp: before its first table, or the setting's own table
    start = 0
    if setting is not None:
        header = re.search(rf"(?m)^\[settings\.{re.escape(json.dumps(setting))}\]$", text)
        if header is None or setting not in section.meta.get("runs", {}):
            raise DvaUsageError(
                f"{path.relative_to(layout.root)} needs a table [settings.{json.dumps(setting)}] with "
                "commit, configs and fingerprint, for a setting of its [runs]"
            )
        start = header.end()
    end = next((start + m.start() for m in re.finditer(r"(?m)^\[", text[start:])), len(text))
    part = text[start:end]
    for key, value in (("commit", commit), ("fingerprint", section.fingerprint(layout, setting))):
        part, count = re.subn(rf'(?m)^{key} = ".*"$', f'{key} = "{value}"', part)
        if count != 1:
            raise DvaUsageError(f"{path.relative_to(layout.root)} needs one line '{key} = \"…\"' there")
    path.write_text(text[:start] + part + text[end:])
