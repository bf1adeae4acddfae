"""Figures for the docs from a finished run and its ground truth.

    .venv/bin/python docs/make_figures.py runs/sample sample_data/sample.gt.npz docs/figures

Writes labelled_cloud.png (the report's labelled-cloud figure of the frame it shows with the
most deforming points: the cloud coloured by class in a camera's image and in 3D),
template_error.png (template coloured by its distance to the true surface) and
registered_vs_true.png (a section through the tool contact at the deepest frame).
"""

from __future__ import annotations

import sys
from pathlib import Path

import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from surgrecon_cli.config import load_config
from surgrecon_cli.core.classify.labels import DEFORMING
from surgrecon_cli.core.evaluate.scoring import map_to_surface
from surgrecon_cli.io.run.artefacts import read_registration, read_template
from surgrecon_cli.io.run.layout import RunLayout
from surgrecon_cli.report.figures import cloud_key, figure_tasks
from surgrecon_cli.report.gather import gather, gather_views
from surgrecon_cli.report.metrics import measure


def labelled_cloud(run: Path, out: Path) -> None:
    """The report's labelled-cloud figure of the frame it shows with the most deforming
    points, as the report draws it."""
    layout = RunLayout(run)
    config = load_config(layout.config_toml)
    data = gather(layout.root)
    views = gather_views(layout, data, config.tool)
    tasks = {t.key: t for t in figure_tasks(data, measure(data, config), views, config)}
    view = max(views, key=lambda v: -1 if v.labels is None else int((v.labels == DEFORMING).sum()))
    task = tasks[cloud_key(view.frame)]
    (out / "labelled_cloud.png").write_bytes(task.fn(*task.args))


def main(run: Path, gt_path: Path, out: Path, frame: int = 12) -> None:
    labelled_cloud(run, out)
    cloud = read_template(RunLayout(run))
    template, rgb = cloud.points, cloud.rgb
    with np.load(gt_path) as gt:
        vertices, faces = gt["vertices"], gt["faces"]
    mapping = map_to_surface(template, vertices[0], faces)
    error = mapping.distance * 1e3
    mm = template * 1e3
    fig, ax = plt.subplots(1, 3, figsize=(16, 5))
    ax[0].scatter(mm[:, 0], mm[:, 1], c=rgb / 255, s=4)
    ax[0].set_title(f"template, {len(template)} points (observed colour)")
    sc = ax[1].scatter(mm[:, 0], mm[:, 1], c=error, s=4, cmap="viridis", vmax=0.5)
    ax[1].set_title("distance to the true surface (mm)")
    plt.colorbar(sc, ax=ax[1])
    for a in ax[:2]:
        a.set_aspect("equal")
        a.set_xlabel("x (mm)")
        a.set_ylabel("y (mm)")
    ax[2].hist(error, bins=60)
    ax[2].set_xlabel("mm")
    ax[2].set_title(f"median {np.median(error):.3f} mm, p95 {np.percentile(error, 95):.3f} mm, "
                    f"max {error.max():.2f} mm")
    fig.tight_layout()
    fig.savefig(out / "template_error.png", dpi=80)

    truth = mapping.follow(vertices[frame], faces) * 1e3
    registered = read_registration(RunLayout(run), frame, len(template)).registered * 1e3
    err = np.linalg.norm(registered - truth, axis=1)
    fig, ax = plt.subplots(1, 2, figsize=(15, 5.5))
    band = np.abs(mm[:, 1] - 10) < 2.5  # through the simulator's tool contact at y = 10 mm
    ax[0].plot(mm[band, 0], mm[band, 2], ".", color="0.7", ms=4, label="template (frame 0)")
    ax[0].plot(truth[band, 0], truth[band, 2], "o", mfc="none", color="tab:green", ms=5,
               label=f"true position, frame {frame}")
    ax[0].plot(registered[band, 0], registered[band, 2], "x", color="tab:red", ms=4,
               label=f"registered, frame {frame}")
    ax[0].set_xlabel("x (mm)")
    ax[0].set_ylabel("z (mm)")
    ax[0].set_title("section through the tool contact (|y - 10 mm| < 2.5 mm)")
    ax[0].legend()
    sc = ax[1].scatter(mm[:, 0], mm[:, 1], c=err, s=5, cmap="magma", vmax=1.0)
    plt.colorbar(sc, ax=ax[1], label="registration error (mm)")
    ax[1].set_aspect("equal")
    ax[1].set_xlabel("x (mm)")
    ax[1].set_ylabel("y (mm)")
    ax[1].set_title(f"frame {frame}: median {np.median(err):.3f} mm, p95 "
                    f"{np.percentile(err, 95):.3f} mm, max {err.max():.2f} mm")
    fig.tight_layout()
    fig.savefig(out / "registered_vs_true.png", dpi=80)


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]), Path(sys.argv[3]))
