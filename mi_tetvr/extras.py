"""The optional parts of mi_tetvr and the packages that bring them.

``pip install mi_tetvr`` installs the core: rendering, derivatives and mesh files
(Mitsuba, which brings its Dr.Jit, numpy, meshio and tqdm). Everything else is
an *extra*, named by what users do with it::

    pip install "mi_tetvr[recon]"      # fit volumes to images, data sets, metrics, plots
    pip install "mi_tetvr[sfm]"        # photos with or without poses (COLMAP via pycolmap)
    pip install "mi_tetvr[tomo]"       # X-ray scans and the tomography baselines
    pip install "mi_tetvr[vis]"        # VTK: lit isosurfaces, VTK files meshio cannot read
    pip install "mi_tetvr[viewer]"     # the live viewer in the browser (viser)
    pip install "mi_tetvr[cluster]"    # partitioned meshes and sweeps over workers (Ray)
    pip install "mi_tetvr[torch]"      # the renderer as a layer of PyTorch programs
    pip install "mi_tetvr[jax]"        # the renderer as a layer of JAX programs
    pip install "mi_tetvr[all]"        # all of the above

Code that needs an extra imports it where it is used, inside :func:`needs`, so
that a missing package is one line naming the ``pip install`` that brings it
(:class:`MissingExtra`), never a ``ModuleNotFoundError`` from deep inside.
``import mi_tetvr`` imports no extra.
"""
from __future__ import annotations

import contextlib

__all__ = ["EXTRAS", "PACKAGES", "MissingExtra", "needs", "require"]

#: Each extra and what it is for.
EXTRAS = {
    "recon": "fitting volumes to images: data sets, initial meshes, metrics and plots",
    "sfm": "photos and videos with or without poses (structure from motion)",
    "tomo": "measured X-ray scans and the tomography baselines",
    "vis": "VTK's filters and readers: lit isosurfaces, VTK files meshio cannot read",
    "viewer": "the live viewer in the browser",
    "cluster": "partitioned meshes and sweeps over workers",
    "torch": "the renderer as a differentiable layer of PyTorch programs",
    "jax": "the renderer as a differentiable layer of JAX programs",
}

#: The optional packages by the name they are imported as: their name on PyPI.
PACKAGES = {"scipy": "scipy", "trimesh": "trimesh", "pytetwild": "pytetwild",
            "pyvista": "pyvista", "vtkmodules": "vtk", "skimage": "scikit-image",
            "matplotlib": "matplotlib", "PIL": "pillow", "yaml": "pyyaml",
            "imageio_ffmpeg": "imageio-ffmpeg", "pycolmap": "pycolmap", "h5py": "h5py",
            "algotom": "algotom", "astra": "astra-toolbox", "viser": "viser", "ray": "ray",
            "av": "av", "cv2": "opencv-python-headless",
            "torch": "torch", "jax": "jax"}


class MissingExtra(ModuleNotFoundError):
    """An optional package is not installed; the message names the extra that
    brings it (``pip install "mi_tetvr[extra]"``)."""


@contextlib.contextmanager
def needs(extra: str, what: str):
    """Turn a missing package, imported inside the block, into :class:`MissingExtra`.

    Parameters
    ----------
    extra : str
        The extra that brings the packages imported in the block (a key of :data:`EXTRAS`).
    what : str
        What needs them, as the message begins (``"the live viewer"``).

    Examples
    --------
    >>> with needs("viewer", "the live viewer"):
    ...     import viser                                   # doctest: +SKIP
    """
    if extra not in EXTRAS:
        raise ValueError(f"unknown extra {extra!r} (extras: {', '.join(EXTRAS)})")
    try:
        yield
    except MissingExtra:
        raise
    except ModuleNotFoundError as e:
        name = e.name or ""
        if name.split(".")[0] == "mi_tetvr":        # the project's own module: a bug, not an extra
            raise
        top = name.split(".")[0]
        raise MissingExtra(f"{what} needs '{PACKAGES.get(top, top)}', which is not "
                           f"installed: pip install \"mi_tetvr[{extra}]\"",
                           name=name) from None


def require(extra: str, what: str, *modules: str) -> None:
    """Import ``modules`` now (a command's first step), so that a missing one is
    :class:`MissingExtra` before any work is done.

    Examples
    --------
    >>> require("cluster", "mi-tetvr sweep", "ray")          # doctest: +SKIP
    """
    import importlib
    with needs(extra, what):
        for name in modules:
            importlib.import_module(name)
