"""``freipose analyze``: behavioral variables and attribution of a stimulation effect."""

from __future__ import annotations

from pathlib import Path

import click

from freipose.cli._cluster import cluster_config, cluster_options, run_through_executor
from freipose.cli._common import allow_incomplete_option, check_complete, user_errors
from freipose.cli._lazy import DefaultLazyGroup


@click.group(cls=DefaultLazyGroup, default="run", lazy_commands={})
def analyze() -> None:
    """Behavioral variables from poses, and which body parts a stimulation changes.

    \b
    Examples:
      freipose analyze study.toml -o results/
      freipose analyze variables rat1.poses.h5 -o rat1.vars.h5
      freipose analyze floor rat1.poses.h5 rat2.poses.h5 -o floor.toml
      freipose analyze design pilot.toml -o design/ --variable "local_z[Paw Front Right]"
      freipose analyze simulate study/ --preset study
    """  # noqa: D301 (click needs the \b escape)


def _floor_value(value: str) -> str:
    if value in ("world", "auto"):
        return value
    if not Path(value).is_file():
        raise click.BadParameter(
            f"expected 'world', 'auto' or an existing floor TOML file, got {value!r}"
        )
    return value


floor_option = click.option(
    "--floor",
    default="world",
    show_default=True,
    callback=lambda ctx, param, v: _floor_value(v),
    help="Floor plane: 'world' = the plane through the world origin perpendicular to the poses' "
    "up vector (z = 0 after 'freipose calib --origin-frame'); 'auto' = robust fit to the lowest "
    "paw positions; or a floor TOML file (normal = [x, y, z], offset = mm).",
)
skeleton_option = click.option(
    "--skeleton",
    default=None,
    help="Skeleton name (rat, mouse) or TOML file defining the body frame and angles "
    "[default: the poses file's own skeleton, else rat].",
)
gap_option = click.option(
    "--max-gap",
    type=click.FloatRange(min=0),
    default=0.1,
    show_default=True,
    help="Fill missing keypoints by linear interpolation over gaps up to this many seconds; "
    "longer gaps stay missing.",
)
window_option = click.option(
    "--stft-window",
    type=click.IntRange(min=4),
    default=64,
    show_default=True,
    help="STFT window in frames (even); gives window/2+1 frequencies (64 -> 33).",
)


@analyze.command("run")
@click.argument("study", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option(
    "-o",
    "--output",
    "outdir",
    required=True,
    type=click.Path(path_type=Path),
    help="Output folder (created).",
)
@skeleton_option
@floor_option
@gap_option
@window_option
@click.option(
    "--onset-delay",
    type=click.FloatRange(min=0),
    default=0.4,
    show_default=True,
    help="Seconds after each window start before frames count as stimulated.",
)
@click.option(
    "--margin",
    type=click.FloatRange(min=0),
    default=1.5,
    show_default=True,
    help="Frames further than this many seconds from every window are "
    "'not stimulated'; frames closer are ignored.",
)
@click.option(
    "-C",
    "--svm-c",
    "C",
    type=click.FloatRange(min=0, min_open=True),
    default=0.0025,
    show_default=True,
    help="Linear SVM regularization C.",
)
@click.option(
    "--alpha",
    type=click.FloatRange(0, 1, min_open=True, max_open=True),
    default=0.001,
    show_default=True,
    help="Significance level of the Bonferroni-adjusted p-values.",
)
@click.option(
    "--standardize",
    type=click.Choice(["recording", "train"]),
    default="recording",
    show_default=True,
    help="How variables are z-scored before the SVMs: 'recording' uses each recording's "
    "own mean and deviation (removes offsets between recordings such as animal size, which "
    "otherwise can make the full SVM predict a single class); 'train' uses the train "
    "frames' statistics (the original method). Variables constant up to round-off in the "
    "train frames are always left out.",
)
@click.option(
    "--independent-frames",
    is_flag=True,
    help="Chi-squared tests count every frame as independent, as in the original "
    "method (anti-conservative). Default: the effective number of independent "
    "frames from the autocorrelation of labels and predictions.",
)
@click.option(
    "--train-stride",
    type=click.IntRange(min=1),
    default=1,
    show_default=True,
    help="Train on every n-th labelled frame (faster on long recordings).",
)
@click.option(
    "--pre",
    "pre_s",
    type=click.FloatRange(min=0),
    default=5.0,
    show_default=True,
    help="Dynamics: seconds before onset.",
)
@click.option(
    "--post",
    "post_s",
    type=click.FloatRange(min=0),
    default=5.0,
    show_default=True,
    help="Dynamics: seconds after the end of the longest window.",
)
@click.option(
    "--top",
    type=click.IntRange(min=1),
    default=6,
    show_default=True,
    help="Number of top variables whose time courses are plotted.",
)
@click.option(
    "-j",
    "--jobs",
    type=int,
    default=1,
    show_default=True,
    help="Parallel workers for the single-variable SVMs (-1 = all cores).",
)
@click.option("--no-figures", is_flag=True, help="Write the tables only.")
@click.option(
    "--overwrite",
    is_flag=True,
    help="Replace the analysis already in OUTDIR (its tables and figures are removed; its "
    "cached variables are reused when still valid).",
)
@allow_incomplete_option()
def run(
    study: Path,
    outdir: Path,
    skeleton: str | None,
    floor: str,
    max_gap: float,
    stft_window: int,
    onset_delay: float,
    margin: float,
    C: float,
    alpha: float,
    standardize: str,
    independent_frames: bool,
    train_stride: int,
    pre_s: float,
    post_s: float,
    top: int,
    jobs: int,
    no_figures: bool,
    overwrite: bool,
    allow_incomplete: bool,
) -> None:
    """Attribute a stimulation effect to body parts by classification (SVMs).

    STUDY is a TOML file listing recordings (poses, events, animal, condition, split; see
    docs/formats.md). For each (animal, condition) a linear SVM on all variables is trained on
    the train recordings and scored on the test recordings of that animal and of the other
    animals; one SVM per variable gives its F-score and a Bonferroni-corrected chi-squared
    test. Writes classification.csv, attribution.csv, dynamics.csv, top_variables.csv and PNG
    figures to OUTDIR; variables are cached in OUTDIR/variables/ (a rerun with --overwrite
    reuses them). An OUTDIR that is not empty is refused without --overwrite.

    \b
    Example:
      freipose analyze study.toml -o results/ --jobs 4
    """  # noqa: D301 (click needs the \b escape)
    with user_errors():
        from freipose.analysis.config import AttributionConfig
        from freipose.analysis.report import analyze_study
        from freipose.analysis.variables import VariableConfig

        vcfg = VariableConfig(max_gap_s=max_gap, stft_window=stft_window)
        acfg = AttributionConfig(
            C=C,
            onset_delay_s=onset_delay,
            margin_s=margin,
            alpha=alpha,
            n_jobs=jobs,
            train_stride=train_stride,
            pre_s=pre_s,
            post_s=post_s,
            top=top,
            independent_frames=independent_frames,
            standardize=standardize,
        )
        result = analyze_study(
            study,
            outdir,
            skeleton,
            floor,
            vcfg,
            acfg,
            make_figures=not no_figures,
            say=click.echo,
            allow_incomplete=allow_incomplete,
            overwrite=overwrite,
        )
        cls = result.classification
        click.echo(
            f"wrote {outdir}/: classification.csv ({len(cls)} rows), attribution.csv, "
            f"dynamics.csv, top_variables.csv" + ("" if no_figures else ", figures")
        )


@analyze.command("variables")
@click.argument("poses", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option(
    "-o",
    "--output",
    required=True,
    type=click.Path(dir_okay=False, path_type=Path),
    help="Output VARS.h5.",
)
@skeleton_option
@floor_option
@gap_option
@window_option
@allow_incomplete_option()
@cluster_options(chunks=False)
@click.pass_context
def variables(
    ctx: click.Context,
    poses: Path,
    output: Path,
    skeleton: str | None,
    floor: str,
    max_gap: float,
    stft_window: int,
    allow_incomplete: bool,
    executor: str | None,
    cluster_file: Path | None,
    parallel: int | None,
    max_retries: int | None,
) -> None:
    """Compute the behavioral variables of a poses file.

    Keypoints in the body frame and their velocities, distances to the body origin and to
    the floor with their velocities and STFTs, and the skeleton's angles (docs/formats.md,
    VARS.h5): 9 + 2F per keypoint and 2 per angle, with F = STFT window / 2 + 1
    frequencies. The 12-keypoint rat with 6 angles has 912 at the default 64-frame
    window and 528 at 32 frames (freipose demo). Poses of several animals give each animal's
    variables, named after it (animal_0/local_z[Nose]), then its social variables towards
    the others (distances, facing, contact: animal_0/facing[animal_1]).

    With --executor (or --cluster FILE) the file is one unit, run in a worker process
    (local) or as a SLURM job; an existing OUTPUT is kept. `freipose jobs OUTPUT` shows it.

    \b
    Example:
      freipose analyze variables rat1.poses.h5 -o rat1.vars.h5 --floor auto
      freipose analyze variables rat1.poses.h5 -o rat1.vars.h5 --cluster cluster.toml
    """  # noqa: D301 (click needs the \b escape)
    with user_errors():
        from freipose.analysis.io import (
            variables_from_poses,
            variables_settings,
            write_variables_h5,
        )
        from freipose.analysis.variables import VariableConfig
        from freipose.io.poses import read_poses_h5

        cfg = VariableConfig(max_gap_s=max_gap, stft_window=stft_window)
        config = cluster_config(executor, cluster_file, None, parallel, max_retries)
        check_complete(poses, allow_incomplete)
        if config is not None:
            from freipose.cluster.variables import VariablesTask

            task = VariablesTask.of(poses, output, skeleton=skeleton, floor=floor, config=cfg,
                                    threads=config.cpus)  # fmt: skip
            run_through_executor(ctx, task, config, overwrite=False)
            return
        data = read_poses_h5(poses, require_up=True)
        var = variables_from_poses(data, skeleton, floor, cfg, source=str(poses))
        write_variables_h5(var, output, variables_settings(skeleton, floor, cfg), source=poses)
        info = var.info
        click.echo(
            f"wrote {output}: {var.values.shape[1]} variables x {var.num_frames} frames; "
            f"{info['keypoints_interpolated']} keypoint positions interpolated, "
            f"{info['frames_with_nan']} frames with undefined variables"
        )


@analyze.command("floor")
@click.argument(
    "poses", nargs=-1, required=True, type=click.Path(exists=True, dir_okay=False, path_type=Path)
)
@click.option(
    "-o",
    "--output",
    required=True,
    type=click.Path(dir_okay=False, path_type=Path),
    help="Output floor TOML.",
)
@skeleton_option
@allow_incomplete_option()
def floor(
    poses: tuple[Path, ...], output: Path, skeleton: str | None, allow_incomplete: bool
) -> None:
    """Fit the floor plane to the lowest paw positions of one or more poses files.

    \b
    Example:
      freipose analyze floor day1/*.poses.h5 -o floor.toml
    """  # noqa: D301 (click needs the \b escape)
    with user_errors():
        import numpy as np

        from freipose.analysis.floor import FloorError, fit_floor, save_floor
        from freipose.analysis.io import resolve_skeleton
        from freipose.analysis.variables import check_keypoints
        from freipose.io.poses import read_poses_h5

        feet, up = [], None
        for p in poses:
            check_complete(p, allow_incomplete)
            data = read_poses_h5(p, require_up=True)
            skel = resolve_skeleton(data, skeleton)
            check_keypoints(data.keypoints, skel, str(p))
            if not skel.feet:
                raise FloorError(f"skeleton {skel.name!r} lists no 'feet' to fit the floor to")
            if up is not None and float(up @ data.up) < 0.999:
                raise FloorError(f"{p}: up vector {data.up.tolist()} differs from {up.tolist()}")
            up = data.up
            feet.append(data.poses[:, list(skel.feet)].reshape(-1, 3))
        plane = fit_floor(np.concatenate(feet), up)
        save_floor(plane, output)
        tilt = np.degrees(np.arccos(np.clip(plane.normal @ up, -1, 1)))
        click.echo(
            f"wrote {output}: normal {np.round(plane.normal, 4).tolist()}, "
            f"offset {plane.offset:.2f} mm (tilt {tilt:.2f} deg from up)"
        )


def _int_list(ctx: click.Context, param: click.Parameter, value: str) -> tuple[int, ...]:
    try:
        out = tuple(sorted({int(v) for v in value.split(",") if v.strip()}))
    except ValueError:
        raise click.BadParameter(
            f"expected whole numbers separated by commas, got {value!r}"
        ) from None
    if not out or min(out) < 1:
        raise click.BadParameter(f"expected numbers >= 1, got {value!r}")
    return out


@analyze.command("design")
@click.argument("study", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option(
    "--variable",
    required=True,
    help="The variable to detect (a name from "
    "attribution.csv, e.g. 'floor_dist_stft_4.69Hz[Paw Front Right]').",
)
@click.option(
    "-o",
    "--output",
    "outdir",
    required=True,
    type=click.Path(file_okay=False, path_type=Path),
    help="Output folder for design.csv and design.png (created; its variables/ cache is reused).",
)
@click.option(
    "--effect",
    type=float,
    default=None,
    help="Effect to detect in standard "
    "deviations of the variable [default: the pilot's own mean effect].",
)
@click.option(
    "--trials",
    default="4,8,16,32,64",
    show_default=True,
    callback=_int_list,
    help="Stimulation trials per animal to try (half train, half test).",
)
@click.option(
    "--animals",
    default="1,2,3",
    show_default=True,
    callback=_int_list,
    help="Numbers of animals to try (the variable must be significant in each).",
)
@click.option(
    "--power",
    "target",
    type=click.FloatRange(0, 1, min_open=True, max_open=True),
    default=0.8,
    show_default=True,
    help="Power wanted.",
)
@click.option(
    "--simulations",
    type=click.IntRange(min=10),
    default=200,
    show_default=True,
    help="Simulated studies per design.",
)
@click.option(
    "--alpha",
    type=click.FloatRange(0, 1, min_open=True, max_open=True),
    default=0.001,
    show_default=True,
    help="Significance level of the analysis.",
)
@click.option(
    "--onset-delay",
    type=click.FloatRange(min=0),
    default=0.4,
    show_default=True,
    help="As for 'freipose analyze'.",
)
@click.option(
    "--margin",
    type=click.FloatRange(min=0),
    default=1.5,
    show_default=True,
    help="As for 'freipose analyze'.",
)
@skeleton_option
@floor_option
@gap_option
@window_option
@click.option("--seed", type=int, default=0, show_default=True, help="Random seed.")
def design(
    study: Path,
    variable: str,
    outdir: Path,
    effect: float | None,
    trials: tuple[int, ...],
    animals: tuple[int, ...],
    target: float,
    simulations: int,
    alpha: float,
    onset_delay: float,
    margin: float,
    skeleton: str | None,
    floor: str,
    max_gap: float,
    stft_window: int,
    seed: int,
) -> None:
    """Estimate from pilot recordings how many trials and animals find an effect.

    STUDY is a pilot study (the manifest of 'freipose analyze'). Every stimulation window
    of its recordings, with the frames around it, is a trial of VARIABLE; simulated
    studies resample these trials, add the effect to the stimulated frames and run the
    analysis' single-variable test per animal (docs/explanation/statistics.md). Prints and
    writes the power of every design (design.csv, design.png) and the fewest trials per
    animal that reach --power.

    \b
    Example:
      freipose analyze design pilot/study.toml -o design/ \\
          --variable "floor_dist[Paw Front Right]" --effect 0.5
    """  # noqa: D301 (click needs the \b escape)
    with user_errors():
        from freipose.analysis.config import AttributionConfig
        from freipose.analysis.design import pilot_trials, power_table, recommended
        from freipose.analysis.figures import power_curves, safe_name
        from freipose.analysis.io import cached_variables
        from freipose.analysis.study import check_study_events, load_study
        from freipose.analysis.variables import VariableConfig
        from freipose.io.atomic import atomic_path

        if min(trials) < 2:
            raise click.BadParameter("every animal needs at least 2 trials (train and test)",
                                     param_hint="--trials")  # fmt: skip
        pilot_study = load_study(study)
        check_study_events(pilot_study)
        vcfg = VariableConfig(max_gap_s=max_gap, stft_window=stft_window)
        cfg = AttributionConfig(onset_delay_s=onset_delay, margin_s=margin, alpha=alpha)
        skel = skeleton if skeleton is not None else pilot_study.skeleton
        variables = {
            r.name: cached_variables(r.poses, outdir / "variables" / f"{safe_name(r.name)}.vars.h5",
                                     skel, r.floor if r.floor is not None else floor, vcfg)
            for r in pilot_study.recordings
        }  # fmt: skip
        pilot = pilot_trials(pilot_study, variables, variable, cfg)
        eff = pilot.mean_effect if effect is None else effect
        click.echo(
            f"pilot: {len(pilot.trials)} trials of {len(pilot.animals)} animal(s); mean effect "
            f"on {variable}: {pilot.mean_effect:.2f} SD; simulating an effect of {eff:.2f} SD, "
            f"Bonferroni over {pilot.n_tested} variables at alpha {alpha:g}"
        )
        table = power_table(pilot, trials, animals, effect, simulations, cfg, seed)
        with atomic_path(outdir / "design.csv") as tmp:
            table.to_csv(tmp, index=False, float_format="%.4g")
        power_curves(table, target, outdir / "design.png", f"{variable}: effect {eff:.2f} SD")
        for row in table.itertuples():
            click.echo(f"  {row.trials:4d} trials x {row.animals} animal(s): power "
                       f"{row.power:.2f} ({row.power_low:.2f}-{row.power_high:.2f}); "
                       f"significant in {row.power_per_animal:.0%} of the animals")  # fmt: skip
        for a, n in recommended(table, target).items():
            click.echo(f"  {a} animal(s): " + (f"{n} trials per animal reach power {target:g}"
                       if n else f"none of the tried trial numbers reaches power {target:g}; "
                       "try more (--trials)"))  # fmt: skip
        click.echo(f"wrote {outdir}/design.csv and design.png")


@analyze.command("simulate")
@click.argument("outdir", type=click.Path(file_okay=False, path_type=Path))
@click.option(
    "--preset",
    type=click.Choice(["pilot", "study"]),
    default="study",
    show_default=True,
    help="pilot: the demo's design (1 animal, a train and a test "
    "day of 30 s); study: 3 animals, 4 train and 4 test days of 30 s each.",
)
@click.option("--seed", type=int, default=0, show_default=True, help="Random seed.")
@click.option(
    "--true-poses",
    is_flag=True,
    help="Write the true keypoints (default: with "
    "the error model of the demo's pose network, 5 mm median, persisting ~0.2 s).",
)
def simulate(outdir: Path, preset: str, seed: int, true_poses: bool) -> None:
    """Write a synthetic stimulation study as poses files (no videos) to OUTDIR.

    The synthetic rat of 'freipose synth' behaves freely while its right front paw is
    lifted and oscillates at 5 Hz during 2 s windows (2 s apart); OUTDIR/study.toml is
    ready for 'freipose analyze' and 'freipose analyze design'.

    \b
    Example:
      freipose analyze simulate study/ --preset study
      freipose analyze study/study.toml -o results/ --stft-window 32 --onset-delay 0.6 \\
          --margin 0.5
    """  # noqa: D301 (click needs the \b escape)
    with user_errors():
        from freipose.synth.study import STUDY_PRESETS, write_study

        p = STUDY_PRESETS[preset]
        path = write_study(outdir, p, seed, with_error=not true_poses)
        click.echo(
            f"wrote {path}: {p.animals} animal(s) x {p.days} recordings of "
            f"{p.frames / p.fps:.0f} s ({p.train_days} train, {p.days - p.train_days} test "
            f"per animal), {'true poses' if true_poses else 'poses with the error model'}"
        )
