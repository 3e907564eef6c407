"""``mi-tetvr process-data IMAGES|VIDEO -o DIR``: camera poses and sparse points of photos
or a video by structure from motion (pycolmap), written as a COLMAP data set for ``fit``;
``--reference DATA`` compares the poses with known cameras."""
from __future__ import annotations

from pathlib import Path

from mi_tetvr.cli import flags
from mi_tetvr.cli.common import CommandError
from mi_tetvr.extras import require

NAME = "process-data"
HELP = ("camera poses of photos or a video by structure from motion (COLMAP through "
        "pycolmap, CPU): a COLMAP data set for fit")


def add_arguments(p):
    p.add_argument("images", help="folder of photos (.jpg, .png, ...) or a video file")
    flags.out(p, "data set folder: images/, database.db, sparse/0 (a COLMAP data set for fit "
                 "and eval)")
    p.add_argument("--matcher", choices=("exhaustive", "sequential"),
                   help="image pairs matched: all (default for photos) or neighbours in name "
                   "order (default for a video)")
    p.add_argument("--max-image-size", type=int, default=1600,
                   help="longest image side for feature extraction (default 1600)")
    p.add_argument("--camera-model", default="SIMPLE_RADIAL",
                   help="COLMAP camera model (default SIMPLE_RADIAL; SIMPLE_PINHOLE, PINHOLE, "
                   "RADIAL, OPENCV, ...)")
    p.add_argument("--camera-per-image", action="store_true",
                   help="fit intrinsics per photo (photos from different cameras or zooms)")
    p.add_argument("--max-frames", type=int, default=100,
                   help="frames taken evenly from a video (default 100)")
    p.add_argument("--reference", help="a data set with known cameras of the same images "
                   "(NeRF-style or COLMAP): print the pose errors after a similarity alignment")
    flags.quiet(p)


_PRIOR = {"exif": "the EXIF focal length", "exif for some photos": "the EXIF focal length of "
          "some photos", "guess": "a guess, 1.2 x the longest side", "given": "the given one"}


def run(a):
    require("sfm", "mi-tetvr process-data", "pycolmap", "PIL")
    from mi_tetvr.recon.sfm import run_sfm
    try:
        s = run_sfm(a.images, a.out, matcher=a.matcher, max_image_size=a.max_image_size,
                    camera_model=a.camera_model, max_frames=a.max_frames,
                    single_camera=not a.camera_per_image, progress=not a.quiet)
    except (ValueError, FileNotFoundError) as e:
        raise CommandError(str(e)) from None
    cam = s["camera"]
    print(f"{a.out}: registered {s['images_registered']} of {s['images_given']} images, "
          f"{s['points']:,} points, mean reprojection error "
          f"{s['mean_reprojection_error']:.2f} px, mean track length "
          f"{s['mean_track_length']:.2f}, {s['seconds']:.1f} s ({cam['model']} "
          f"f = {cam['params'][0]:.1f} px, started from {_PRIOR[s['focal_prior']]}) "
          f"-> {s['model']}")
    if a.reference:
        compare(a.out, a.reference)
    print(f"next: mi-tetvr fit {a.out} --out {Path(a.out).with_name(Path(a.out).name + '_fit')}"
          f"  (add --downscale N for large photos)")


def compare(model, reference):
    """Print the pose errors of the cameras found (``model``) against those of
    ``reference`` with the same image names, after a similarity alignment."""
    from mi_tetvr.recon.datasets import load_colmap, load_dataset
    from mi_tetvr.recon.sfm import align_cameras
    try:
        ref = load_dataset(reference, holdout=None, load_images=False)
        est = load_colmap(model, holdout=None, load_images=False)
    except (ValueError, FileNotFoundError) as e:
        raise CommandError(f"--reference: {e}") from None
    ref_cams = {Path(v.name).stem: v.camera for v in ref.views}
    pairs = [(v.camera, ref_cams[Path(v.name).stem]) for v in est.views
             if Path(v.name).stem in ref_cams]
    if len(pairs) < 3:
        print(f"against {reference}: {len(pairs)} image name(s) in common, at least 3 "
              f"are needed to compare the cameras")
        return
    r = align_cameras([p[0] for p in pairs], [p[1] for p in pairs])
    print(f"against {reference} ({len(pairs)} images in common, similarity scale "
          f"{r['scale']:.4g}): rotation error mean {r['rotation_error_deg_mean']:.2f}, "
          f"median {r['rotation_error_deg_median']:.2f}, max "
          f"{r['rotation_error_deg_max']:.2f} deg (relative rotations: max "
          f"{r['relative_rotation_error_deg_max']:.2f} deg); position error mean "
          f"{100 * r['position_error_mean']:.2f} %, median "
          f"{100 * r['position_error_median']:.2f} %, max "
          f"{100 * r['position_error_max']:.2f} % of the reference cameras' extent "
          f"(bounding-box diagonal {r['scene_size']:.4g})")
