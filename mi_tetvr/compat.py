"""The Mitsuba releases mi_tetvr runs on.

The range is written in one place, the package's requirement on ``mitsuba``
(``pyproject.toml``, read back from the installed package's metadata), and
checked when ``mi_tetvr`` is imported: outside it, the import fails with one
line naming the installed release and the supported range. The documentation's
*Mitsuba versions* page says which of Mitsuba's APIs the package relies on, and
what its next release changes.
"""
from __future__ import annotations

from importlib import metadata

__all__ = ["supported_mitsuba", "check_mitsuba"]


def supported_mitsuba() -> str | None:
    """The supported Mitsuba releases as a version specifier (``"~=3.9.1"``),
    from the installed package's requirements; None where mi_tetvr runs from
    a source tree that is not installed (nothing to check against)."""
    try:
        requirements = metadata.requires("mi_tetvr") or []
    except metadata.PackageNotFoundError:
        return None
    from packaging.requirements import Requirement
    for text in requirements:
        req = Requirement(text)
        if req.name == "mitsuba" and req.marker is None:
            return str(req.specifier) or None
    return None


def check_mitsuba(version: str | None = None, supported: str | None = None) -> None:
    """Raise ``ImportError`` where Mitsuba's ``version`` (default: the
    installed one) lies outside ``supported`` (default:
    :func:`supported_mitsuba`)."""
    from packaging.specifiers import SpecifierSet
    from packaging.version import InvalidVersion, Version
    if version is None:
        import mitsuba
        version = getattr(mitsuba, "__version__", "unknown")
    supported = supported_mitsuba() if supported is None else supported
    if not supported:
        return
    try:
        ok = SpecifierSet(supported).contains(Version(version), prereleases=True)
    except InvalidVersion:
        ok = False
    if not ok:
        try:
            ours = metadata.version("mi_tetvr")
        except metadata.PackageNotFoundError:
            ours = "(a source tree)"
        raise ImportError(f"mi_tetvr {ours} runs on Mitsuba {supported}, and the "
                          f"installed Mitsuba is {version}: pip install \"mitsuba{supported}\"")
