"""Speed against accuracy of voxel renders: DAGs at 256^3..8192^3 against the triangle mesh.

For each mesh (default: the Stanford bunny, spot and the cow):

* a reference: the triangle mesh path-traced with Embree (`jaxvox.render_mesh`) at many
  samples per pixel (``--reference-spp``);
* the mesh again at the sweep's samples per pixel (``--spp``), its noise level;
* the mesh's DAG at each resolution, rendered by `jaxvox.render` with the same settings,
  shaded with the normal of the voxel face each ray enters (``dag``) and with per-voxel
  shading normals, the face normal of the triangle that set each voxel (``dag-normals``:
  `jaxvox.mesh_to_dag` with ``attributes=``, so that 8192^3 fits), the same with the
  thin 6-separating voxelization instead of the conservative one (``dag-thin``: a
  conservative silhouette stands out by most of a voxel), and with the boundary of the
  solid voxelization (``dag-solid``: `jaxvox.solid_boundary`, voxels whose centres are
  inside, so that silhouettes straddle the surface instead of enclosing it; normals of
  each voxel's closest triangle; built in one piece, up to 4096^3 here).

The lighting is the procedural sky with its sun, 8 bounces, grey albedo 0.7. Every case
runs in a fresh subprocess (peak memory is its own). Time per sample is the median of
``--repeats`` timed renders after a compiling one, divided by the pixel samples; the
voxelization and DAG build are timed apart. Errors are PSNR and SSIM (scikit-image) of the
tone-mapped sRGB image (what a viewer sees; values in [0, 1]) against the reference's.

Writes ``experiments/results/render_vs_mesh.{json,md,png}`` (chart: time per sample
against PSNR, SSIM against resolution) and ``render_vs_mesh_strip.png`` (the images).
``--smoke`` runs two small resolutions at a small size in a few minutes. ``--device gpu``
runs every case on JAX's GPU backend (``JAX_PLATFORMS``); the default is JAX's default.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import _common
import numpy as np

DEFAULT_MESHES = ("stanford-bunny", "spot", "cow")
SOLID_MAX = 4096  # largest R of the dag-solid case (its voxels are found in one piece)


def _metrics(image: np.ndarray, reference: np.ndarray) -> dict:
    from skimage.metrics import peak_signal_noise_ratio, structural_similarity

    a, b = image.astype(np.float64) / 255.0, reference.astype(np.float64) / 255.0
    return dict(
        psnr=float(peak_signal_noise_ratio(b, a, data_range=1.0)),
        ssim=float(structural_similarity(b, a, channel_axis=-1, data_range=1.0)),
    )


def worker(spec: dict) -> dict:
    import jax

    import jaxvox as jv
    from jaxvox.io.images import write_png

    mesh = jv.load_mesh(_common.MESH_DIR / f"{spec['mesh']}.obj")
    eye, target = jv.look_at_view(mesh, azimuth=spec["azimuth"], elevation=20.0, distance=1.6)
    settings = dict(
        env=jv.sky_environment(),
        width=spec["width"],
        height=spec["height"],
        spp=spec["spp"],
        bounces=spec["bounces"],
        key=spec["seed"],
        progress=False,
    )
    out = Path(spec["out"])
    row = dict(mesh=spec["mesh"], case=spec["case"], spp=spec["spp"])
    if spec["case"] in ("reference", "mesh"):
        run = lambda: jv.render_mesh(mesh, eye, target, **settings)
    else:
        R = spec["resolution"]
        start = time.perf_counter()
        grid = jv.Grid.fit(mesh, resolution=R)
        if spec["case"] == "dag-solid":
            vox = jv.solid_boundary(mesh, grid, triangle_ids=True)
            settings["normals"] = jv.voxel_attributes(mesh, vox)["normal"]
            tree = jv.build_dag(vox)
            del vox
        elif spec["case"] in ("dag-normals", "dag-thin"):
            import tempfile

            folder = tempfile.mkdtemp(dir=out)
            mode = "6-separating" if spec["case"] == "dag-thin" else "conservative"
            tree, attributes = jv.mesh_to_dag(mesh, grid, attributes=folder, mode=mode)
            settings["normals"] = attributes["normal"]
        else:
            tree = jv.build_dag(jv.voxelize(mesh, grid))
        tree.mask.block_until_ready()
        row.update(
            resolution=R,
            build_s=time.perf_counter() - start,
            dag_bytes=int(tree.compact_nbytes),
            voxels=int(tree.voxel_count),
        )
        run = lambda: jax.block_until_ready(jv.render(tree, eye, target, **settings))
    repeats = 0 if spec["case"] == "reference" else spec["repeats"]
    timing, result = _common.time_calls(run, repeats)
    samples = spec["width"] * spec["height"] * spec["spp"]
    row.update(
        timing=timing,
        ns_per_sample=timing["median_s"] / samples * 1e9,
        peak_rss_mib=_common.peak_rss_mib(),
        stopped=int(result.stopped),
    )
    image = jv.tonemap(result.radiance)
    name = f"{spec['mesh']}_{spec['case']}" + (f"_{spec['resolution']}" if spec["case"].startswith("dag") else "")
    write_png(out / f"{name}.png", image)
    if spec["case"] == "reference":
        jv.save_render(out / f"{name}.exr", result)
    else:
        import imageio.v3 as iio

        row.update(_metrics(image, iio.imread(out / f"{spec['mesh']}_reference.png")))
    row["image"] = f"{name}.png"
    row["backend"] = jax.default_backend()
    if spec["case"] in ("dag-normals", "dag-thin"):
        import shutil

        del settings["normals"], attributes
        shutil.rmtree(folder, ignore_errors=True)
    return row


def chart(rows: list[dict], path: Path) -> None:
    fig, (left, right) = _common.new_figure(2)
    for mesh in sorted({r["mesh"] for r in rows}):
        line = None
        for case, style, label in (
            ("dag", "o-", "DAG, face normals"),
            ("dag-normals", "s--", "DAG, voxel normals"),
            ("dag-thin", "^:", "6-separating DAG, voxel normals"),
            ("dag-solid", "d-.", "solid-boundary DAG, voxel normals"),
        ):
            dags = sorted((r for r in rows if r["mesh"] == mesh and r["case"] == case), key=lambda r: r["resolution"])
            if not dags:
                continue
            colour = None if line is None else line.get_color()
            (line,) = left.plot(
                [r["ns_per_sample"] for r in dags],
                [r["psnr"] for r in dags],
                style,
                color=colour,
                label=f"{mesh} {label}",
            )
            for r in dags:
                left.annotate(
                    f"{r['resolution']}",
                    (r["ns_per_sample"], r["psnr"]),
                    textcoords="offset points",
                    xytext=(4, 4),
                    fontsize=8,
                )
            right.plot(
                [r["resolution"] for r in dags],
                [r["ssim"] for r in dags],
                style,
                color=line.get_color(),
                label=f"{mesh} {label}",
            )
        for r in rows:
            if r["mesh"] == mesh and r["case"] == "mesh":
                left.plot(
                    [r["ns_per_sample"]],
                    [r["psnr"]],
                    "*",
                    ms=12,
                    color=line.get_color(),
                    label=f"{mesh} mesh (Embree), same spp",
                )
                right.axhline(r["ssim"], ls="--", color=line.get_color(), label=f"{mesh} mesh, same spp")
    left.set(
        xscale="log",
        xlabel="time per pixel sample (ns, 8 bounces)",
        ylabel="PSNR vs reference (dB)",
        title="speed against accuracy (2-core CPU)",
    )
    right.set(xscale="log", xlabel="DAG resolution R", ylabel="SSIM vs reference", title="structure against R")
    right.set_xscale("log", base=2)
    left.legend(fontsize=8)
    right.legend(fontsize=8)
    _common.save_figure(fig, path)


def strip(rows: list[dict], folder: Path, path: Path) -> None:
    import imageio.v3 as iio

    lines = []
    for mesh in sorted({r["mesh"] for r in rows}):
        mine = [r for r in rows if r["mesh"] == mesh]
        order = (
            [r for r in mine if r["case"] == "reference"]
            + [r for r in mine if r["case"] == "mesh"]
            + sorted((r for r in mine if r["case"] == "dag"), key=lambda r: r["resolution"])
            + sorted((r for r in mine if r["case"] == "dag-normals"), key=lambda r: r["resolution"])
            + sorted((r for r in mine if r["case"] == "dag-thin"), key=lambda r: r["resolution"])
            + sorted((r for r in mine if r["case"] == "dag-solid"), key=lambda r: r["resolution"])
        )
        tiles = [iio.imread(folder / r["image"]) for r in order if (folder / r["image"]).exists()]
        gap = np.full((tiles[0].shape[0], 6, 3), 255, np.uint8)
        lines.append(np.concatenate([x for t in tiles for x in (t, gap)][:-1], axis=1))
    width = max(line.shape[1] for line in lines)
    lines = [np.pad(line, ((0, 6), (0, width - line.shape[1]), (0, 0)), constant_values=255) for line in lines]
    iio.imwrite(path, np.concatenate(lines, axis=0))


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--meshes", nargs="+", default=list(DEFAULT_MESHES))
    parser.add_argument("--resolutions", nargs="+", type=int, default=[256, 512, 1024, 2048, 4096, 8192])
    parser.add_argument("--size", default="320x240")
    parser.add_argument("--spp", type=int, default=16)
    parser.add_argument("--reference-spp", type=int, default=256)
    parser.add_argument("--bounces", type=int, default=8)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument(
        "--cases",
        nargs="+",
        default=["dag", "dag-normals", "dag-thin", "dag-solid"],
        choices=["dag", "dag-normals", "dag-thin", "dag-solid"],
    )
    parser.add_argument("--device", default=None, help="cpu or gpu (JAX_PLATFORMS for every case); default: JAX's")
    parser.add_argument("--smoke", action="store_true")
    parser.add_argument("--out", type=Path, default=_common.RESULTS_DIR)
    parser.add_argument("--worker")
    args = parser.parse_args()
    if _common.answer_as_worker(args, worker):
        return
    if args.device:
        os.environ["JAX_PLATFORMS"] = args.device
    if args.smoke:
        args.size, args.spp, args.reference_spp, args.resolutions, args.repeats = "64x48", 2, 8, [32, 64], 1
    width, height = (int(x) for x in args.size.split("x"))
    stem = "render_vs_mesh" + ("_smoke" if args.smoke else "")
    images = args.out / stem
    images.mkdir(parents=True, exist_ok=True)
    rows = []
    for mesh in _common.progress(args.meshes, desc="meshes"):
        base = dict(
            mesh=mesh,
            width=width,
            height=height,
            bounces=args.bounces,
            repeats=args.repeats,
            out=str(images),
            azimuth=35.0 if mesh != "spot" else 145.0,
        )
        cases = [dict(case="reference", spp=args.reference_spp, seed=12345), dict(case="mesh", spp=args.spp, seed=0)]
        cases += [
            dict(case=c, resolution=R, spp=args.spp, seed=0)
            for R in args.resolutions
            for c in args.cases
            if c != "dag-solid" or R <= SOLID_MAX  # built in one piece
        ]
        for case in cases:
            row = _common.run_worker(__file__, dict(base, **case), timeout=7200)
            if "error" in row:
                print(f"{mesh} {case}: {row['error']}", file=sys.stderr)
                if case["case"] == "reference":
                    break
                continue
            rows.append(row)
            print(
                f"{mesh} {case['case']} {case.get('resolution', '')}: {row['ns_per_sample']:.0f} ns/sample, "
                f"PSNR {row.get('psnr', float('nan')):.2f} dB, SSIM {row.get('ssim', float('nan')):.4f}, "
                f"{row['peak_rss_mib']:.0f} MiB",
                flush=True,
            )
            _common.write_json(
                args.out / f"{stem}.json",
                dict(
                    machine=_common.machine_info(["jax", "embreex", "numpy", "scikit-image"]),
                    settings=dict(
                        width=width, height=height, spp=args.spp, reference_spp=args.reference_spp, bounces=args.bounces
                    ),
                    rows=rows,
                ),
            )
    columns = [
        ("mesh", "mesh"),
        ("case", "render"),
        ("resolution", "R"),
        ("spp", "spp"),
        ("ns", "ns / sample"),
        ("psnr", "PSNR dB"),
        ("ssim", "SSIM"),
        ("build", "voxelize + DAG s"),
        ("mib", "DAG MiB"),
        ("rss", "peak RSS MiB"),
    ]
    table = [
        dict(
            mesh=r["mesh"],
            case=r["case"],
            resolution=r.get("resolution", "-"),
            spp=r["spp"],
            ns=f"{r['ns_per_sample']:.0f}",
            psnr=f"{r['psnr']:.2f}" if "psnr" in r else "-",
            ssim=f"{r['ssim']:.4f}" if "ssim" in r else "-",
            build=f"{r['build_s']:.1f}" if "build_s" in r else "-",
            mib=f"{r['dag_bytes'] / 2**20:.1f}" if "dag_bytes" in r else "-",
            rss=f"{r['peak_rss_mib']:.0f}",
        )
        for r in rows
    ]
    md = _common.markdown_table(table, columns)
    (args.out / f"{stem}.md").write_text(md + "\n")
    print(md)
    if any(r["case"].startswith("dag") for r in rows):
        chart(rows, args.out / f"{stem}.png")
        strip(rows, images, args.out / f"{stem}_strip.png")


if __name__ == "__main__":
    main()
