"""Commands on models: fit the AnyLoc vocabulary, export a model to ONNX, list and verify model files."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Annotated

import typer

from meridian_torch.cli.common import (
    ConfigOption,
    SetOption,
    config_from_options,
    error_boundary,
    progress_bar,
)

__all__ = ["export_onnx", "fit_vocabulary", "models_list", "models_verify"]


@error_boundary
def fit_vocabulary(
    images: Annotated[list[Path], typer.Argument(help="RGB images (PNG/JPEG) representative of the domain.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Vocabulary file to write (.pt).")],
    seed: Annotated[int, typer.Option(help="Seed of the token subsampling and k-means initialization.")] = 0,
    tokens_per_image: Annotated[
        int | None, typer.Option(help="Random tokens kept per image (default: all), bounds memory.", min=1)
    ] = None,
    config: ConfigOption = None,
    set_: SetOption = None,
) -> None:
    """Fit the AnyLoc VLAD vocabulary (cosine k-means) of perception.global_descriptor.anyloc.

    Tokens are the configured backbone/layer/facet of IMAGES; the number of clusters is
    perception.global_descriptor.anyloc.num_clusters. Point vocabulary_path at OUT to use it.
    """
    import numpy as np
    import torch
    from PIL import Image, UnidentifiedImageError

    from meridian_torch.errors import ConfigError
    from meridian_torch.perception.factory import build_anyloc_facet
    from meridian_torch.perception.neural import anyloc
    from meridian_torch.runtime import resolve_runtime

    cfg = config_from_options(config, set_)
    c = cfg.perception.global_descriptor.anyloc
    runtime = resolve_runtime(cfg.runtime)
    facet = build_anyloc_facet(c).to(device=runtime.device, dtype=runtime.dtype)

    def read_rgb(path: Path) -> torch.Tensor:
        try:
            with Image.open(path) as img:
                rgb = np.asarray(img.convert("RGB"), dtype=np.float32) / 255.0
        except (OSError, UnidentifiedImageError) as e:
            raise ConfigError(f"{path}: not a readable image ({e})") from None
        return torch.from_numpy(rgb).permute(2, 0, 1)[None]

    started = time.perf_counter()
    try:
        with progress_bar("extracting tokens", "image") as update:
            centers = anyloc.fit_vocabulary(
                facet, (read_rgb(p) for p in images), num_clusters=c.num_clusters,
                resize_short_side_px=c.resize_short_side_px, seed=seed, tokens_per_image=tokens_per_image,
                progress=update, total=len(images),
            )
    except ValueError as e:
        raise ConfigError(f"fit-vocabulary: {e}") from None
    vocabulary = anyloc.Vocabulary(centers, architecture=c.architecture, layer=c.layer, facet=c.facet)
    anyloc.save_vocabulary(out, vocabulary)
    typer.echo(
        f"wrote {out}: {centers.shape[0]} centres of dimension {centers.shape[1]} from {len(images)} images "
        f"({time.perf_counter() - started:.1f} s)"
    )


@error_boundary
def export_onnx(
    model: Annotated[str, typer.Argument(help="dinov2-dense, anyloc-facet, vlad-head, sam-encoder or sam-decoder.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="ONNX file to write.", dir_okay=False)],
    config: ConfigOption = None,
    set_: SetOption = None,
    exporter: Annotated[str | None, typer.Option(help="legacy or dynamo (default: the model's, legacy).")] = None,
) -> None:
    """Export a model as configured (weights, architecture, layer, vocabulary) to ONNX.

    The graph is written only after onnxruntime reproduces eager torch on two input sizes; the
    max abs differences are printed. dinov2-dense comes from perception.descriptor.dinov2,
    anyloc-facet and vlad-head from perception.global_descriptor.anyloc, sam-* from
    perception.aerial_segmenter.sam. Point perception.onnx.* at the files to run them onboard.
    """
    from meridian_torch.export.models import EXPORTABLE_MODELS, export_model

    if model not in EXPORTABLE_MODELS:
        raise typer.BadParameter(f"{model!r}; exportable: {', '.join(EXPORTABLE_MODELS)}", param_hint="MODEL")
    if exporter not in (None, "legacy", "dynamo"):
        raise typer.BadParameter(f"{exporter!r}; use legacy or dynamo", param_hint="--exporter")
    cfg = config_from_options(config, set_)
    started = time.perf_counter()
    report = export_model(model, cfg.perception, out, exporter=exporter)  # type: ignore[arg-type]
    shapes = ", ".join(f"{name}{list(shape)}" for name, shape in report.inputs.items())
    checked = "; ".join(f"{list(c.input_shapes)}: {max(c.max_abs_diff.values()):.2g}" for c in report.checks)
    typer.echo(f"wrote {out} ({report.size_bytes / 2**20:.1f} MiB, {report.exporter} exporter, "
               f"{time.perf_counter() - started:.1f} s); inputs {shapes}")
    typer.echo(f"max abs difference to torch (tolerance {report.atol:g} + {report.rtol:g}*|x|): {checked}")


ManifestOption = Annotated[
    Path | None,
    typer.Option("--manifest", dir_okay=False, help="Model manifest, files beside it (default: the models folder's "
                 "manifest.yaml, else the shipped one; the models folder is $MERIDIAN_TORCH_MODELS, the checkout's "
                 "models/ or ~/.local/share/meridian-torch/models)."),
]


@error_boundary
def models_list(manifest: ManifestOption = None) -> None:
    """List the known model files, whether each is present, and where to get it."""
    from meridian_torch.export.manifest import load_manifest

    m = load_manifest(manifest)
    for e in m.entries:
        present = "present" if (m.folder / e.file).is_file() else "missing"
        recorded = "sha256 recorded" if e.sha256 else "no hash recorded"
        typer.echo(f"{e.name:24s} {present:8s} {recorded:17s} {e.file}\n{'':24s} {e.architecture}; {e.license}\n"
                   f"{'':24s} {e.source}")
    typer.echo(f"{len(m.entries)} models in {m.path}; files go in {m.folder}")


@error_boundary
def models_verify(
    names: Annotated[list[str] | None, typer.Argument(help="Models to check (default: every file present).")] = None,
    manifest: ManifestOption = None,
    record: Annotated[bool, typer.Option(help="Write the sha256 of present files that have none into the "
                                              "manifest (recorded hashes are never overwritten).")] = False,
) -> None:
    """Hash model files and compare with the manifest: ok, mismatch, missing or no hash recorded.

    Exits 1 on a mismatch, or when a model named on the command line is missing.
    """
    from meridian_torch.export.manifest import load_manifest, verify_models

    m = load_manifest(manifest)
    results = verify_models(m, names or (), record=record)
    for r in results:
        if r.status == "missing" and not names:
            continue  # without names, only the files the user has are checked
        detail = {"mismatch": f"file {r.sha256} != manifest {r.entry.sha256}", "missing": f"no file {r.path}",
                  "no hash recorded": "run `models verify --record` to record it"}.get(r.status, r.sha256 or "")
        typer.echo(f"{r.entry.name:24s} {r.status:17s} {detail}")
    checked = [r for r in results if names or r.status != "missing"]
    if not checked:
        from meridian_torch.core.paths import shipped_dir

        typer.echo(f"no model files in {m.folder} (see {shipped_dir('models') / 'README.md'})")
    failed = [r.entry.name for r in checked if r.failed]
    if failed:
        typer.echo(f"error: {', '.join(failed)} failed verification", err=True)
        raise typer.Exit(1)
