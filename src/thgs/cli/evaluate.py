"""``thgs eval``: score a semantic field on the benchmarks' protocols."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import tyro
from rich.table import Table

from thgs.choices import Device
from thgs.cli._console import StageBars, setup_logging, stage_progress, stdout
from thgs.cli._outputs import check_output_file
from thgs.errors import InputError

__all__ = ["evaluate", "evaluate_mean"]


def _report_table(title: str, report) -> Table:
    table = Table(title=title, title_justify="left")
    for column in ("protocol", "metric", "value", "scored"):
        table.add_column(column)
    for result in report.results:
        for name, value in result.metrics.items():
            table.add_row(result.protocol, name, f"{value:.4f}", str(len(result.items)))
    return table


def evaluate(
    dataset: Annotated[Path, tyro.conf.arg(metavar="DATASET")],
    field: Annotated[Path, tyro.conf.arg(metavar="FIELD")],
    /,
    *,
    protocol: tuple[str, ...] = (),
    labels: Path | None = None,
    segmentations: Path | None = None,
    scannet: Path | None = None,
    openhype: Path | None = None,
    scannet_level: int = 3,
    out: Annotated[Path | None, tyro.conf.arg(aliases=("-o",))] = None,
    scene: Path | None = None,
    text_model: Path | None = None,
    device: Device = "auto",
    other_scene: bool = False,
    rescale_labels: bool = False,
    verbose: bool = False,
) -> None:
    """Score a semantic field against a benchmark's ground truth.

    Runs every protocol whose ground truth is in DATASET (or those named with --protocol),
    prints a table and writes the full report (every frame and prompt) as JSON and the table as
    markdown beside it.

    Args:
        dataset: the scene's dataset folder: label/ (LERF-OVS), segmentations/ (3D-OVS),
            scannet/*.labels.ply (ScanNet), ground_truth.safetensors (synthetic), and beside it
            openhype_scannetpp_benchmark/<scene>/ (OpenHype's ScanNet++ objects and parts).
        field: the field file (thgs build).
        protocol: registered protocols (thgs.eval.protocols): lerf (THGS: 3D selection →
            rendered mask), lerf-langsplat (2D relevancy maps), lerf-opengaussian (silhouette >
            0.7), 3dovs, openhype (ScanNet++ objects and "[PART] of a [OBJ]" parts), scannet,
            hierarchy (synthetic levels); default: all with ground truth.
        labels: the LERF-OVS labels, if neither in DATASET/label nor in LangSplat's
            DATASET/../label/<scene>: the scene's folder (lerf_ovs/label/teatime) or the folder
            of every scene (lerf_ovs/label: its <scene>/ is taken, <scene> being DATASET's
            name); decides when both places hold labels.
        segmentations: the 3D-OVS segmentations folder, if not DATASET/segmentations.
        scannet: the ScanNet label PLY (<scene>_vh_clean_2.labels.ply), if not in DATASET.
        openhype: the OpenHype annotation folder of the scene (its *.json and mask PNGs), or
            the folder of every scene's (openhype_scannetpp_benchmark: its <scene>/ is taken),
            if not beside DATASET.
        scannet_level: the field level whose features classify ScanNet points (3: objects).
        out: the JSON report (default: <field>.eval.json); the table goes to the same name .md.
        scene: the scene the field was built on, if not where the field says.
        text_model: the text model's local folder, instead of the one the field records (or,
            for a field that records none, the Hugging Face cache).
        device: where to render: auto (a CUDA GPU if torch sees one, else MPS, else the CPU),
            cpu, cuda or mps (docs/rendering.md).
        other_scene: score DATASET even though its cameras are not the field's scene's
            (refused by default: its ground truth belongs to another capture).
        rescale_labels: stretch 2-D labels whose aspect ratio is not their camera's (refused by
            default; labels of the same aspect ratio at another size are always scaled).
        verbose: log what is loaded and how long it takes.
    """
    from thgs.eval.dataset import find_ground_truth
    from thgs.eval.protocols import get_protocol, sources
    from thgs.workflows import EvalRequest, eval_table_path, evaluate_field_file

    setup_logging(verbose)
    out = out if out is not None else field.with_suffix(".eval.json")
    check_output_file(out)
    check_output_file(eval_table_path(out))
    for name in protocol:
        get_protocol(name)  # an unknown name stops here, before any loading
    ground_truth = find_ground_truth(
        dataset, lerf=labels, three_dovs=segmentations, scannet=scannet, openhype=openhype
    )
    if not protocol and not ground_truth.available():
        places = "; ".join(source.describe for source in sources())
        raise InputError(
            dataset,
            f"holds no benchmark ground truth ({places}); name it with --labels, "
            "--segmentations, --scannet or --openhype",
        )
    request = EvalRequest(
        dataset=dataset,
        field=field,
        out=out,
        protocols=protocol or None,
        scannet_level=scannet_level,
        scene=scene,
        text_model=text_model,
        device=device,
        other_scene=other_scene,
        rescale_labels=rescale_labels,
    )
    with stage_progress() as bar:
        outcome = evaluate_field_file(request, ground_truth, progress=StageBars(bar))
    report = outcome.report
    stdout.print(_report_table(f"{ground_truth.scene_name}: {field.name}", report))
    for note in report.notes():
        stdout.print(note, highlight=False)
    stdout.print(f"report: {outcome.json_path} (table: {outcome.table_path})")


def evaluate_mean(
    reports: Annotated[tuple[Path, ...], tyro.conf.arg(metavar="REPORT")],
    /,
    *,
    out: Annotated[Path | None, tyro.conf.arg(aliases=("-o",))] = None,
) -> None:
    """Average thgs eval reports of several scenes: every protocol's metrics, mean over scenes.

    The last step of the protocols' averaging (LERF-OVS: prompts → frames → scenes), to put
    beside published numbers.

    Args:
        reports: one thgs eval JSON report per scene.
        out: also write the means as JSON.
    """
    from thgs._json import load_json
    from thgs.eval.dataset import mean_over_scenes
    from thgs.export import write_json

    if not reports:
        raise InputError("thgs eval-mean", "give one report per scene")
    if out is not None:
        check_output_file(out)
    documents = [load_json(path) for path in reports]
    for path, document in zip(reports, documents):
        if not isinstance(document, dict) or not isinstance(document.get("results"), list):
            raise InputError(path, "is not a thgs eval report (no 'results' list)")
    means = mean_over_scenes(documents)
    table = Table(title=f"mean over {len(reports)} scenes", title_justify="left")
    for column in ("protocol", "metric", "mean"):
        table.add_column(column)
    for protocol, metrics in means.items():
        for name, value in metrics.items():
            table.add_row(protocol, name, f"{value:.4f}")
    stdout.print(table)
    if out is not None:
        write_json(out, {"scenes": [str(p) for p in reports], "means": means})
        stdout.print(f"wrote {out}")
