"""Frames of one scene from many cameras, their kernels recorded once.

``mi.render`` in Python traces the integrator's code on every call (Dr.Jit
records its operations, then compiles the kernel or finds it in its cache).
For the small images of a live viewer or of an orbit, tracing takes longer
than running the kernel: ``benchmarks/bench_viewer.py`` measures both.
``dr.freeze`` records the kernel launches of a first call and replays them
for later calls whose inputs are laid out alike; :class:`Frames` renders
through it, keeping one sensor per film and field of view whose pose it
updates (a new sensor object would be a new input and a new recording).

Sensors are described by dictionaries (``mi.load_dict``'s, e.g.
:meth:`Frames.camera_dict` of a :class:`~mi_tetvr.camera.Camera`). Where Dr.Jit
cannot record a render (it reads arrays that the inputs do not reach, such
as a probe's isovalues held by a plain Python object), the frames of that
integrator are traced as ``mi.render`` traces them. What a replay does not
see: Python state of the plugins (an integrator's
settings, a shape's index buffers, values a plugin keeps between renders).
So a :class:`Frames` belongs to one scene, keeps one recording per
integrator object, and is to be :meth:`cleared <Frames.clear>` (or made
anew) whenever anything but the camera changes.
"""
from __future__ import annotations

#: Recordings kept per integrator (the least recently used go first).
RECORDINGS = 16


def _trace(scene, sensor, integrator, seed):
    import mitsuba as mi
    return mi.render(scene, sensor=sensor, integrator=integrator, seed=seed)


class Frames:
    """Renders ``scene`` from :class:`~mi_tetvr.camera.Camera` s (pinhole),
    replaying recorded kernels where it can (``freeze=False``: plain
    ``mi.render``, e.g. for a comparison)."""

    def __init__(self, scene, freeze: bool = True):
        self.scene = scene
        self.freeze = bool(freeze)
        self._sensors = {}
        self._recorded = {}

    def clear(self):
        """Forget the recordings (after a change of the scene's parameters,
        shapes or integrators' settings)."""
        self._recorded.clear()

    def sensor(self, d):
        """The kept sensor of a sensor dictionary ``d`` (one per dictionary
        but for its ``to_world``), posed as ``d`` says."""
        import mitsuba as mi
        key = repr({k: v for k, v in d.items() if k != "to_world"})
        sensor = self._sensors.get(key)
        if sensor is None:
            sensor = self._sensors[key] = mi.load_dict(d)
        params = mi.traverse(sensor)
        params["to_world"] = d["to_world"]
        params.update()
        return sensor

    @staticmethod
    def camera_dict(camera, spp=1):
        """The sensor dictionary of a :class:`~mi_tetvr.camera.Camera`: an RGBA
        film, ``spp`` stratified samples (jittered when more than one)."""
        d = camera.sensor_dict(spp=spp, sampler="stratified", jitter=spp > 1)
        d["film"]["pixel_format"] = "rgba"
        return d

    def render(self, camera, integrator=None, spp=1, seed=0):
        """The image (``mi.TensorXf``, RGBA) from ``camera`` with
        ``integrator`` (None: the scene's)."""
        return self.render_dict(self.camera_dict(camera, spp), integrator, seed)

    def render_dict(self, d, integrator=None, seed=0):
        """The image (``mi.TensorXf``) of the sensor dictionary ``d``."""
        import drjit as dr
        import mitsuba as mi
        sensor = self.sensor(d)
        with dr.suspend_grad():
            if not self.freeze:
                return _trace(self.scene, sensor, integrator, int(seed))
            key = id(integrator)
            entry = self._recorded.get(key)
            if entry is None:
                # (the integrator is held: its id stays its own; one recording
                # per film size and spp: a viewer's few sizes)
                entry = self._recorded[key] = (integrator, dr.freeze(
                    _trace, limit=RECORDINGS, warn_after=RECORDINGS))
            if entry[1] is None:
                return _trace(self.scene, sensor, integrator, int(seed))
            try:
                return entry[1](self.scene, sensor, integrator, mi.UInt32(int(seed)))
            except RuntimeError:
                # Dr.Jit refuses to record a render that reads arrays it cannot
                # reach from the inputs (a plugin's own Python objects): trace it.
                self._recorded[key] = (integrator, None)
                return _trace(self.scene, sensor, integrator, int(seed))
