"""The ``adarl`` command: run, inspect, resume and evaluate recipes.

Errors that adarl raises on purpose (bad recipe, existing run folder, corrupt checkpoint) print one clear line
and exit with status 2 (bad input) or 1; nothing is written for a recipe that does not validate.

Each command imports the wing it runs (the recipe runtime, the experiment tooling) when it runs, not at the top:
``adarl --help`` and a typo answer at once, without torch, TorchRL or MuJoCo, and ``--quiet`` takes effect before
any of them is imported (:func:`_quiet_env`). What is imported at the top here is light.

Long because: every subcommand's parser, with the help text users read, is here beside the command it calls, so
that ``adarl --help`` stays one light import; what each command does lives in its wing.
"""

from __future__ import annotations

import argparse
import errno
import os
import signal
import sys
import time
import warnings
from pathlib import Path

from adarl import __version__
from adarl.errors import (
    STORAGE_ERRNOS,
    AdaRLError,
    AdaRLValueError,
    AdaRLWarning,
    RecipeError,
    command,
    describe_name_too_long,
    describe_os_error,
    did_you_mean,
)
from adarl.experiments import tune
from adarl.experiments.bench import add_arguments as bench_arguments
from adarl.experiments.launcher_args import add_launcher_arguments, launcher_options
from adarl.runtime.signals import GracefulInterrupt, RunInterrupted, silence_stdout, stdout_reader_gone

__all__ = ["main"]


def _err(msg: str) -> None:
    print(f"adarl: error: {msg}", file=sys.stderr)


def _quiet_env(quiet: bool = False) -> None:
    """Before anything imports TorchRL or MuJoCo: headless rendering, and none of their chatter in the terminal
    (TorchRL's INFO lines, its import-time deprecations, its "no target network updater" warning: adarl updates
    the targets itself). ``quiet`` (``--quiet``) also silences wandb."""
    os.environ.setdefault("MUJOCO_GL", "egl")
    os.environ.setdefault("RL_LOGGING_LEVEL", "WARNING")  # read when torchrl is imported
    if quiet:
        os.environ.setdefault("WANDB_SILENT", "true")
    warnings.filterwarnings("ignore", category=DeprecationWarning)
    warnings.filterwarnings("ignore", category=FutureWarning)
    warnings.filterwarnings("ignore", message=".*WeightUpdaterBase.*")
    warnings.filterwarnings("ignore", message=".*settotalmass.*")
    warnings.filterwarnings("ignore", message="No target network updater has been associated")


def _one_line_warnings() -> None:
    """adarl's own warnings (a skipped checkpoint, an experiment axis that changes nothing) as one line each."""
    plain = warnings.formatwarning

    def fmt(message, category, filename, lineno, line=None):
        if issubclass(category, AdaRLWarning):
            return f"adarl: warning: {message}\n"
        return plain(message, category, filename, lineno, line)

    warnings.formatwarning = fmt


def _run_folder(recipe, output: str | None) -> Path:
    if output:
        return Path(output)
    if recipe.output.dir:
        return Path(recipe.output.dir)
    return Path(recipe.output.root) / f"{recipe.name}-{time.strftime('%Y%m%d-%H%M%S')}"


def _missing_parents(path: Path) -> list[Path]:
    """The folders above ``path`` that do not exist yet, deepest first (``runs/`` for ``runs/name-time``)."""
    out, p = [], path.absolute().parent
    while not p.exists():
        out.append(p)
        p = p.parent
    return out


def _checked_run_folder(run_dir, overrides=()) -> None:
    """What ``adarl resume`` and ``adarl eval`` refuse before they load anything, said before torch is imported (a
    wrong path at once, not after torch's and TorchRL's seconds of import); the trainer opens it again."""
    from adarl.runtime.continuing import open_continued

    open_continued(run_dir, overrides)


def cmd_run(args) -> int:
    # torch-free up to the training: a wrong key, value or output folder is refused at once (tests/test_cli_usability)
    from adarl.runtime.config import load_recipe
    from adarl.runtime.run_folder.run_dir import RunDir, logging_backends

    recipe = load_recipe(args.recipe, args.overrides)  # validates everything before anything is written
    logging_backends(recipe)  # a logging extra that is not installed: refused before any folder is made
    path = _run_folder(recipe, args.output)
    if args.pack_seeds:
        return _run_pack(recipe, args.pack_seeds, path, overwrite=args.overwrite, quiet=args.quiet)
    existed = path.exists()
    parents = _missing_parents(path)
    run_dir = RunDir.create(path, overwrite=args.overwrite)
    try:
        run_dir.save_recipe(recipe)
        from adarl.runtime.trainers import trainer_class  # torch and TorchRL, once the input is known to be valid

        trainer = trainer_class(recipe)(recipe, run_dir, quiet=args.quiet)
    except BaseException:
        # Nothing ran: leave no half-made run folder behind (and never remove one the user had), nor the empty
        # folders above it that were made for it (runs/).
        run_dir.discard(keep_folder=existed)
        for folder in parents:
            try:
                folder.rmdir()
            except OSError:
                break
        raise
    summary = _train(trainer)
    _print_summary(summary, run_dir.path)
    return 0


def _run_pack(recipe, seeds, path: Path, *, overwrite: bool, quiet: bool) -> int:
    """``adarl run RECIPE --pack-seeds S ...``: the seeds side by side in this process (adarl.runtime.trainers.packed),
    one run folder each (``PATH/seed=S``)."""
    from adarl.runtime.trainers.pack_folder import create_pack

    pack = create_pack(recipe, seeds, path, overwrite=overwrite, quiet=quiet)
    return _finish_pack(pack)


def _finish_pack(pack) -> int:
    from adarl.runtime.trainers.pack_folder import finish

    GracefulInterrupt.stopped_at_once = None
    summaries = finish(pack.train())
    for folder, summary in summaries.items():
        _print_summary(summary, Path(folder))
    return 0


def _resume_pack(args) -> int:
    """``adarl resume PACK``: every seed of a pack folder that has not finished, side by side again."""
    from adarl.runtime.trainers.pack_folder import resume_pack

    if args.overrides:
        raise AdaRLError(
            f"a pack folder resumes to its recipe's frames; overrides {args.overrides} are not taken (continue each "
            "seed's run folder on its own to more frames)"
        )
    pack, said = resume_pack(args.run_dir, checkpoint=args.checkpoint, quiet=args.quiet)
    for line in said:
        print(line)
    return 0 if pack is None else _finish_pack(pack)


def _train(trainer) -> dict:
    """``trainer.train()``; a file-system failure (disk full, read-only) becomes one line saying how to go on."""
    GracefulInterrupt.stopped_at_once = None  # set by a second signal during this training only
    try:
        return trainer.train()
    except BaseException as err:
        try:  # envs, workers and metric files; on a full disk, closing must not add errors to the one line below
            trainer.close()
        except Exception:  # noqa: BLE001
            pass
        if GracefulInterrupt.stopped_at_once is not None and not isinstance(err, KeyboardInterrupt):
            # a second signal stopped it at once, wherever it was: what broke under it (a library that wraps the
            # KeyboardInterrupt in its own error) is that stop, said in one line, never a traceback
            raise KeyboardInterrupt from None
        if not isinstance(err, OSError) or err.errno not in STORAGE_ERRNOS:
            raise
        path = trainer.run_dir.path
        what = describe_os_error(err) if err.filename else f"writing in {str(path)!r}: {describe_os_error(err)}"
        raise AdaRLError(
            f"{what}; the run stopped, its last checkpoint is intact: free space (or "
            f"make {str(path)!r} writable) and `{command('adarl', 'resume', path)}`"
        ) from None


def _print_summary(summary: dict, path: Path) -> None:
    from adarl.runtime.report import named_ranks

    ev = summary.get("final_eval") or {}
    ranks = ", ".join(f"{name}={rank}" for name, rank in named_ranks(summary).items()) or "-"
    print(
        f"run finished: {summary['frames']} frames, {summary['updates']} updates, "
        f"{summary['rank_events']} rank events, final ranks {ranks}"
    )
    if ev:
        print(f"nominal-dynamics evaluation: {ev['mean']:.1f} ± {ev['std']:.1f} over {ev['episodes']} episodes")
    stop = summary.get("stopped_early")
    if stop:
        print(f"stopped early at {stop['frames']} frames by callback {stop['callback']!r}: {stop['reason']}")
    print(f"results: {path}  (report: {path / 'report.md'})")


def cmd_resume(args) -> int:
    from adarl.runtime.continuing import already_complete
    from adarl.runtime.trainers.pack_folder import is_pack_folder

    if is_pack_folder(args.run_dir):
        return _resume_pack(args)
    _checked_run_folder(args.run_dir, args.overrides)
    from adarl.runtime.trainers import BaseTrainer

    trainer = BaseTrainer.resume(args.run_dir, quiet=args.quiet, checkpoint=args.checkpoint, overrides=args.overrides)
    total = trainer.recipe.collector.total_frames
    done = already_complete(args.run_dir, trainer.frames, total, stopped=trainer.stopped_early)
    if done is not None:  # its latest checkpoint is at the end: say so (exit 0) instead of finishing it again
        trainer.close()
        print(done)
        return 0
    summary = _train(trainer)
    _print_summary(summary, Path(args.run_dir))
    return 0


def cmd_recipes(args) -> int:
    from adarl.runtime.config import EXPERIMENTS_DIR, TUNE_DIR, list_recipes
    from adarl.runtime.config.discovery import list_specs

    sections = [
        ("", list_recipes()),  # the recipes first, unheaded: `adarl recipes | head` shows recipes
        ("experiment specs (adarl experiment NAME)", list_specs(EXPERIMENTS_DIR)),
        ("tune specs (adarl tune NAME; or adarl tune RECIPE: its default search space)", list_specs(TUNE_DIR)),
    ]
    width = max((len(n) for _, rows in sections for n, _ in rows), default=10)
    for title, rows in sections:
        if title:
            print(f"\n{title}:")
        for name, desc in rows:
            print(f"{name:<{width}}  {desc}")
    return 0


def cmd_show(args) -> int:
    from adarl.runtime.config import load_recipe, recipe_to_yaml

    print(recipe_to_yaml(load_recipe(args.recipe, args.overrides)), end="")
    return 0


def cmd_eval(args) -> int:
    if args.sweep:
        from adarl.experiments.sweep import parse_sweep, sweep_run

        result = sweep_run(
            args.run_dir,
            [parse_sweep(s) for s in args.sweep],
            episodes=args.episodes,
            name=args.name,
            checkpoint=args.checkpoint,
        )
        print(result.describe())
        return 0

    _checked_run_folder(args.run_dir)
    from adarl.runtime.evaluation import describe_returns, evaluate_policy
    from adarl.runtime.trainers import BaseTrainer

    # read-only: the training records (metrics, ranks, checkpoints, summary) are left exactly as training wrote them
    trainer = BaseTrainer.resume(args.run_dir, quiet=True, read_only=True, checkpoint=args.checkpoint)
    recipe = trainer.recipe
    episodes = args.episodes or recipe.eval.episodes
    result = evaluate_policy(
        trainer.c.modules.actor, trainer.c.eval_env, episodes=episodes, max_steps=recipe.eval.max_steps
    )
    trainer.close()
    out = Path(args.run_dir) / "eval_nominal.json"
    trainer.run_dir.write_json(out.name, {"frames": trainer.frames, "episodes": episodes, **result.as_dict()})
    said = describe_returns(result.mean, result.std, result.ci95, episodes)
    print(f"nominal-dynamics evaluation at {trainer.frames} frames: {said} -> {out}")
    return 0


def cmd_play(args) -> int:
    from adarl.runtime.play import parse_perturb, play

    size = _size(args.size)
    result = play(
        args.run,
        which=args.which,
        episodes=args.episodes,
        video=args.video,
        perturb=parse_perturb(args.perturb),
        max_steps=args.max_steps,
        seed=args.seed,
        size=size,
    )
    dyn = ", ".join(f"{k}={v:g}" for k, v in result.dynamics.items()) or "the env's own"
    print(f"policy of {result.checkpoint} ({result.frames} frames), dynamics: {dyn}")
    for i, (ret, n) in enumerate(zip(result.returns, result.lengths)):
        print(f"episode {i}: return {ret:.1f} over {n} steps")
    if result.video is not None:
        print(f"video: {result.video}")
    return 0


def cmd_export(args) -> int:
    from adarl.runtime.export import export_policy

    result = export_policy(
        args.run, args.output, which=args.which, format=args.format, layers=args.layers, overwrite=args.overwrite
    )
    print(result.describe())
    return 0


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
        if w < 16 or h < 16:
            raise ValueError
    except ValueError:
        raise AdaRLValueError(f"--size {text!r} must be WIDTHxHEIGHT in pixels (each >= 16), e.g. 480x480") from None
    return w, h


def cmd_bench(args) -> int:
    from adarl.experiments.bench import cli

    return cli(args)


def cmd_report(args) -> int:
    from adarl.experiments.report import is_single_run, write_aggregate_report
    from adarl.experiments.spec import load_experiment, report_options
    from adarl.runtime.report import write_report

    dirs = args.run_dir
    options, spec_values = {}, {}  # checked first: a bad spec or option writes nothing
    if args.spec is not None:
        spec = load_experiment(args.spec)
        options = {k: v for k, v in spec.report.model_dump().items() if v not in (None, [])}
        spec_values = {axis: {v.name for v in values} for axis, values in spec.axes.items()}  # its pairs name these
    given = report_options(args.report_options)
    options.update(given)
    if len(dirs) == 1 and is_single_run(dirs[0]) and not args.output and set(options) <= {"formats"}:
        print(write_report(dirs[0], **options))  # one run folder: its own report, as before (--set formats=...)
        return 0
    # --set pairs=... (or verdict_seeds per arm): each value must be the column axis's, of a run found or of the
    # spec (a typo is refused)
    pair_values = spec_values if given.get("pairs") or isinstance(options.get("verdict_seeds"), dict) else None
    print(write_aggregate_report(dirs, args.output, report=options, pair_values=pair_values))
    return 0


def cmd_experiment(args) -> int:
    from adarl.experiments.orchestrate import run_experiment
    from adarl.experiments.progress import use_live
    from adarl.experiments.spec import load_experiment
    from adarl.runtime.run_folder.results import is_url

    options = launcher_options(args)
    live = not args.no_live and use_live()
    progress = args.progress
    if progress is None:  # a live board redraws often; plain lines every 30 s; a URL costs requests per refresh
        target = args.output if args.output is not None else load_experiment(args.spec).output
        progress = (10.0 if is_url(target) else 2.0) if live else 30.0
    try:
        runs = run_experiment(
            args.spec,
            budget=args.budget,
            output=args.output,
            workers=args.workers,
            dry_run=args.dry_run,
            report=not args.no_report,
            launcher=args.launcher,
            launcher_options=options,
            progress_interval=progress,
            scratch=args.scratch,
            live=live,
            rerun_changed=args.rerun_changed,
            pack=args.pack,
        )
    except KeyboardInterrupt:  # stopped at once (a second signal, or a launcher that stops its runs so)
        _err(
            "experiment interrupted (stopped at once; each run keeps its previous checkpoint): run the same "
            "`adarl experiment` command to resume it"
        )
        return 130
    if not args.dry_run:
        counts: dict[str, int] = {}
        for r in runs:
            counts[r.status] = counts.get(r.status, 0) + 1
        print("experiment done: " + ", ".join(f"{n} {k}" for k, n in sorted(counts.items())))
    return 0


class _IntermixedParser(argparse.ArgumentParser):
    """A subcommand's parser that takes options and positionals in any order (``adarl run quickstart -o DIR
    seed=1``): argparse's intermixed parsing, which the top-level parser cannot use itself (it has subparsers)."""

    _parsing = False

    def parse_known_args(self, args=None, namespace=None):
        if self._parsing:  # parse_known_intermixed_args calls back into parse_known_args (Python < 3.12)
            return super().parse_known_args(args, namespace)
        self._parsing = True
        try:
            namespace, extras = self.parse_known_intermixed_args(args, namespace)
        finally:
            self._parsing = False
        for arg in extras:
            if arg.startswith("-") and arg != "-":
                self._unknown_option(arg)
        return namespace, extras

    def _unknown_option(self, arg: str) -> None:
        """A mistyped option: this subcommand's usage and the closest of its options (``--ouput``: ``--output``),
        exit status 2, instead of the top-level usage and "unrecognized arguments"."""
        name = arg.split("=", 1)[0]
        options = [o for o in self._option_string_actions if o.startswith("--")] or list(self._option_string_actions)
        self.error(f"unrecognized option {name!r}{did_you_mean(name, options)} (options: {', '.join(sorted(options))})")


def _version() -> str:
    return f"adarl {__version__}"


def build_parser() -> argparse.ArgumentParser:
    """The ``adarl`` parser. It imports nothing heavy (torch, TorchRL): ``adarl --help`` and typos answer at once;
    each command imports what it needs when it runs."""
    p = argparse.ArgumentParser(prog="adarl", description="Robust RL by adaptive rank control, on TorchRL.")
    p.add_argument("--version", action="version", version=_version())
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND", parser_class=_IntermixedParser)

    r = sub.add_parser(
        "run",
        help="train a recipe in a new run folder, evaluate it and write a report",
        description="Train RECIPE (a shipped name, see `adarl recipes`, or a .yaml path). "
        "Overrides are key=value in OmegaConf dotlist style, e.g. rank.beta=0.95.",
    )
    r.add_argument("recipe")
    r.add_argument("overrides", nargs="*", metavar="key=value")
    r.add_argument("--output", "-o", help="run folder (default: output.dir, or output.root/<name>-<time>)")
    r.add_argument("--overwrite", action="store_true", help="replace an existing run folder")
    r.add_argument("--quiet", "-q", action="store_true", help="no progress bar")
    r.add_argument(
        "--pack-seeds",
        nargs="+",
        type=int,
        metavar="SEED",
        help="train these seeds of the recipe side by side in this process, their SAC updates as one batched "
        "program (one run folder each, OUTPUT/seed=S; `adarl resume OUTPUT` continues them; docs/performance.md)",
    )
    r.set_defaults(func=cmd_run)

    rs = sub.add_parser(
        "resume",
        help="continue a run from its latest checkpoint, or a finished one to more frames",
        description="Continue the run in RUN_DIR from its latest loadable checkpoint. A finished run is "
        "continued to more frames with collector.total_frames=M (the budget, raised; recipe.yaml records it); "
        "without it, a finished run is reported as already complete. The other key a resume may change is "
        "callbacks (callbacks=[] lets a run a callback stopped early train on; docs/callbacks.md).",
    )
    rs.add_argument("run_dir")
    rs.add_argument("overrides", nargs="*", metavar="collector.total_frames=M")
    rs.add_argument(
        "--checkpoint",
        choices=["latest"],
        default=None,
        help="insist on the newest checkpoint: fail if it cannot be used, instead of skipping it (with a "
        "warning) for the newest one that loads",
    )
    rs.add_argument("--quiet", "-q", action="store_true", help="no progress bar")
    rs.set_defaults(func=cmd_resume)

    ls = sub.add_parser(
        "recipes",
        help="list the shipped recipes, experiment specs and tune specs",
        description="List the recipes (adarl run NAME), then the experiment specs (adarl experiment NAME) and the "
        "tune specs (adarl tune NAME) of the recipe folders ($ADARL_RECIPES_PATH, then the shipped ones).",
    )
    ls.set_defaults(func=cmd_recipes)

    sh = sub.add_parser(
        "show",
        help="print a recipe fully resolved (extends and overrides applied)",
        description="Print RECIPE resolved and validated, as YAML.",
    )
    sh.add_argument("recipe")
    sh.add_argument("overrides", nargs="*", metavar="key=value")
    sh.set_defaults(func=cmd_show)

    ev = sub.add_parser(
        "eval",
        help="evaluate a run's saved policy on the nominal dynamics",
        description="Evaluate the latest checkpoint of RUN_DIR deterministically on the nominal "
        "dynamics (the centre of the uncertainty set); writes eval_nominal.json.",
    )
    ev.add_argument("run_dir")
    ev.add_argument("--episodes", type=int, default=None, help="episodes (default: the recipe's eval.episodes)")
    ev.add_argument(
        "--checkpoint",
        default=None,
        metavar="latest|best|PATH",
        help="which checkpoint: the best nominal evaluation, a file, or the newest ('latest': fail if it "
        "cannot be used; default: the newest one that loads, a skipped newer one named in a warning)",
    )
    ev.add_argument(
        "--sweep",
        action="append",
        metavar="PARAM=LO:HI:N",
        help="robustness sweep instead: evaluate on a grid of PARAM (others at nominal); give it twice "
        "for a 2-D grid. Writes sweeps/<name>.csv, .json and .png in RUN_DIR",
    )
    ev.add_argument("--name", default=None, help="file stem of the sweep's outputs (default: the parameter names)")
    ev.set_defaults(func=cmd_eval)

    pl = sub.add_parser(
        "play",
        help="watch a run's policy act (headless), optionally recorded to an MP4 video",
        description="Run the policy of RUN (a run folder or a checkpoint file) deterministically on "
        "the nominal dynamics (the evaluations' centre of the training schedule), or on "
        "dynamics set with --perturb, and print each episode's return; with --video, "
        "render headless (MUJOCO_GL=egl or osmesa) into one MP4 file (needs moviepy: "
        "pip install 'adarl[video]').",
    )
    pl.add_argument("run", metavar="RUN")
    pl.add_argument("--video", default=None, metavar="OUT.mp4", help="record the episodes to this MP4 file")
    pl.add_argument("--episodes", "-n", type=int, default=1, help="episodes to play (default: 1)")
    pl.add_argument(
        "--perturb",
        action="append",
        default=[],
        metavar="PARAM=V",
        help="set a dynamics parameter (e.g. torso_length=0.5); give it again for another",
    )
    pl.add_argument(
        "--which",
        choices=["latest", "best"],
        default="latest",
        help="with a run folder: its latest checkpoint (default) or the best evaluation's",
    )
    pl.add_argument(
        "--max-steps", type=int, default=None, help="steps per episode (default: the recipe's eval.max_steps)"
    )
    pl.add_argument("--seed", type=int, default=0, help="seed of the env's initial states (default: 0)")
    pl.add_argument("--size", default="480x480", metavar="WxH", help="video frame size (default: 480x480)")
    pl.set_defaults(func=cmd_play)

    xp = sub.add_parser(
        "export",
        help="write a run's policy as a self-contained program (TorchScript, torch.export or ONNX)",
        description="Write the deterministic policy of RUN (a run folder or a checkpoint file) as one file that "
        "torch alone loads (no adarl, TorchRL or tensordict), with its metadata inside: observation in, "
        "action (scaled to the env's bounds) out. Checked against the run's TorchRL actor before it is "
        "written. Load it with adarl.ExportedPolicy(FILE).predict(obs) or torch.jit.load (docs/quickstart.md).",
    )
    xp.add_argument("run", metavar="RUN")
    xp.add_argument(
        "--output", "-o", default=None, metavar="FILE", help="file to write (default: RUN/policy.pt, .pt2, .onnx)"
    )
    xp.add_argument(
        "--format",
        choices=["torchscript", "export", "onnx"],
        default="torchscript",
        help="torchscript (default, .pt: torch.jit.load), export (.pt2: torch.export.load) or onnx (needs the onnx "
        "and onnxscript packages)",
    )
    xp.add_argument(
        "--layers",
        choices=["auto", "merged", "factored"],
        default="auto",
        help="low-rank layers as one merged W1 @ W2 or as two factors; auto: whichever is cheaper at each "
        "layer's rank (default)",
    )
    xp.add_argument("--which", choices=["latest", "best"], default="latest", help="with a run folder: which checkpoint")
    xp.add_argument("--overwrite", action="store_true", help="replace an existing FILE")
    xp.set_defaults(func=cmd_export)

    rp = sub.add_parser(
        "report",
        help="write a run's report, or aggregate many runs into one report",
        description="One run folder: (re)write its report.md and plots/ (each figure as PNG, PDF and SVG; "
        "--set formats=[png] for PNG alone). Several folders (run folders, experiment folders, or folders holding "
        "runs), or --output: aggregate them across seeds into report.md/report.html, figures (PNG, PDF, SVG) and "
        "CSV tables.",
    )
    rp.add_argument("run_dir", nargs="+", metavar="DIR", help="a folder, or an fsspec URL (s3://bucket/exp, ...)")
    rp.add_argument(
        "--output",
        "-o",
        default=None,
        help="folder (or fsspec URL) of the aggregate report (default: <DIR>/report for one experiment "
        "folder, else ./report)",
    )
    rp.add_argument(
        "--spec",
        default=None,
        metavar="SPEC",
        help="take the report section (scoring rule, plateau, reference, pairs, ...) of this experiment spec (a "
        "file, or a shipped name such as table1) over the experiments' own: loose run folders reported by its rule",
    )
    rp.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        dest="report_options",
        help="a key of an experiment spec's report section, over the experiments' and --spec's (repeatable): e.g. "
        "--set score_last=3 --set plateau=1500 --set reference=adarl reports loose run folders by issue 34's "
        "protocol (keys: score_last, plateau, reference, pairs, verdict_seeds, columns, x_axis, intrinsic_rank, "
        "event_window, at_updates)",
    )
    rp.set_defaults(func=cmd_report)

    bn = sub.add_parser(
        "bench",
        help="side-by-side SAC speed benchmark (AdaRL-SAC, no-rank, stock TorchRL, SB3)",
        description="Interleaved, repeated (median) speed benchmark of AdaRL-SAC against the same loop "
        "without rank adaptation, a stock TorchRL SAC loop and Stable-Baselines3 SAC (when installed: "
        "pip install 'adarl[bench]'). Prints a table and writes a JSON report. --whole-run: whole runs "
        "instead, timed from process start to exit (docs/performance.md, 'Whole runs'). --pack: N seeds packed in "
        "one process against the same N seeds solo (docs/performance.md, 'Packed seeds').",
    )
    bench_arguments(bn)
    bn.set_defaults(func=cmd_bench)
    ex = sub.add_parser(
        "experiment",
        help="run a multi-run experiment spec (axes x seeds), resumably",
        description="Run every run of the experiment SPEC (a YAML file with kind: experiment, or a shipped spec's "
        "name: `adarl recipes` lists them under 'experiment specs') one after another or in worker processes; "
        "finished runs "
        "are skipped, interrupted ones resumed; then write the aggregate report.",
    )
    ex.add_argument("spec")
    ex.add_argument("--budget", "-b", default=None, help="a budget named in the spec (e.g. small)")
    ex.add_argument(
        "--output",
        "-o",
        default=None,
        help="output folder, or an fsspec URL (s3://bucket/exp, gs://..., file:///shared/exp; the "
        "backend package, e.g. s3fs, must be installed) that runs upload to (default: the spec's, or "
        "runs/experiments/<name>-<budget>)",
    )
    ex.add_argument(
        "--scratch",
        default=None,
        metavar="DIR",
        help="with a URL output: local folder each run trains in before it is uploaded (default: "
        "$TMPDIR/adarl-scratch on the machine the run lands on)",
    )
    ex.add_argument("--workers", "-j", type=int, default=None, help="runs at a time (default: the spec's workers)")
    ex.add_argument(
        "--pack",
        type=int,
        default=None,
        metavar="N",
        help="train the seeds of one arm N at a time in one process, their SAC updates one batched program (default: "
        "the spec's pack, 1; docs/performance.md, 'Packed seeds'); an arm that cannot be packed runs solo, said why",
    )
    ex.add_argument("--dry-run", action="store_true", help="list the runs and their status; run nothing")
    ex.add_argument("--no-report", action="store_true", help="do not write the aggregate report")
    ex.add_argument(
        "--rerun-changed",
        action="store_true",
        help="train again the runs whose folder was made from another recipe than the spec plans now (refused "
        "otherwise, naming the keys that changed), into new folders beside the old ones (<run id>.rerun1; the old "
        "folders are kept)",
    )
    add_launcher_arguments(ex)
    ex.add_argument(
        "--progress",
        type=float,
        default=None,
        metavar="SECONDS",
        help="refresh the progress board (one row per run, an aggregate bar) this often; 0: only report "
        "runs as they end (default: 30 for plain lines, 2 for the live board, 10 for it with a URL)",
    )
    ex.add_argument(
        "--no-live",
        action="store_true",
        help="plain progress lines even on a terminal (the live board is used only when stdout is a "
        "terminal and CI is not set)",
    )
    ex.set_defaults(func=cmd_experiment)
    tu = sub.add_parser("tune", help=tune.HELP, description=tune.DESCRIPTION)
    tune.add_arguments(tu)
    tu.set_defaults(func=tune.cli)
    return p


def _restore_sigint() -> None:
    """A process started in the background by a non-interactive shell (``adarl experiment ... &`` in a script)
    inherits SIGINT ignored, and Python then leaves it ignored: ``kill -INT`` would do nothing. Restore Python's
    handler so that SIGINT stops adarl as Ctrl-C does (a terminal's Ctrl-C never reaches background jobs anyway)."""
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)


def _line_buffered_stdout() -> None:
    """Each output line is written when printed, also into a pipe or a file (Python buffers 8 KB there): a
    ``| tee log`` shows an experiment's progress as it happens, and a reader that has gone is noticed at the next
    line, not hours later."""
    reconfigure = getattr(sys.stdout, "reconfigure", None)
    if reconfigure is not None:
        try:
            reconfigure(line_buffering=True)
        except (ValueError, OSError):  # a replaced stdout that cannot (detached, closed)
            pass


def main(argv: list[str] | None = None) -> int:
    if argv is None:  # the process's own command line: it ends once a stop was asked (never a caller's process)
        GracefulInterrupt.process_ends_after_a_stop = True
    _restore_sigint()
    _line_buffered_stdout()
    args = build_parser().parse_args(argv)
    _quiet_env(bool(getattr(args, "quiet", False)))
    _one_line_warnings()
    try:
        status = int(args.func(args) or 0)
        sys.stdout.flush()  # here, not at the interpreter's exit: a closed pipe is then caught below
        return status
    except BrokenPipeError:
        if not stdout_reader_gone():
            raise
        silence_stdout()  # as a Unix tool killed by SIGPIPE: no traceback, exit 128 + 13
        return 128 + signal.SIGPIPE
    except RunInterrupted as err:  # SIGINT/SIGTERM: a checkpoint was saved, the run can be resumed
        _err(str(err))
        return err.exit_code
    except RecipeError as err:
        _err(str(err))
        return 2
    except AdaRLError as err:
        _err(str(err))
        return 2 if isinstance(err, ValueError) else 1
    except OSError as err:  # disk full, read-only, no permission: one line, not a traceback
        if err.errno == errno.ENAMETOOLONG:  # a name given that is too long: bad input, not the disk failing
            _err(describe_name_too_long(err))
            return 2
        if err.errno not in STORAGE_ERRNOS:
            raise
        _err(describe_os_error(err))
        return 1
    except KeyboardInterrupt:
        _err("interrupted (stopped at once; the run folder keeps its previous checkpoint: `adarl resume RUN_DIR`)")
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
