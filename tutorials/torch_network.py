"""Tutorial: a PyTorch network that maps vertex positions to colors and
opacities, trained through the renderer.

The renderer is a differentiable layer of a PyTorch program here
(:func:`mi_tetvr.interop.ray_renderer`): PyTorch tensors in (the vertices'
colors and opacities, the rays), RGBA per ray out, and ``loss.backward()``
runs the renderer's own adjoint and hands its gradients on to the network's
weights. Nothing of the fit is Mitsuba's but the render.

1. A *target* volume (a jittered tet grid carrying a blob of color and
   opacity) is rendered from ``--views`` cameras around it (one ray through
   each pixel centre).
2. The network: Fourier features of each vertex's position, two hidden layers,
   then colors in [0, 1] (a sigmoid) and opacities >= 0 (a softplus).
3. Each step draws ``--rays`` rays at random from all the photos (as NeRF
   trainers do), renders them with the network's colors and opacities on the
   same mesh, and takes an Adam step of the L2 loss over RGBA.
4. Held-out views (cameras between the training ones) score the network:
   PSNR of the sRGB pictures over black. The picture shows a held-out view:
   the target, the network's render, and the loss over the steps.

Run it with::

    python tutorials/torch_network.py
    python tutorials/torch_network.py --steps 600 --res 96

It needs PyTorch (``pip install "mi_tetvr[torch]"``).
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

import mitsuba as mi


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--cells", type=int, default=12, help="grid cells per axis (default 12)")
    p.add_argument("--views", type=int, default=16, help="training views (default 16)")
    p.add_argument("--res", type=int, default=64, help="image size (default 64)")
    p.add_argument("--steps", type=int, default=300, help="Adam steps (default 300)")
    p.add_argument("--rays", type=int, default=4096, help="rays per step (default 4096)")
    p.add_argument("--lr", type=float, default=5e-3, help="Adam's step (default 5e-3)")
    p.add_argument("--out", default="out/torch_network")
    p.add_argument("--variant", default="llvm_ad_rgb")
    p.add_argument("--quiet", action="store_true")
    return p.parse_args(argv)


def network(torch, frequencies=4, hidden=64):
    """Vertex positions (n, 3) -> colors (n, 3) in [0, 1] and opacities (n,) >= 0."""
    class Field(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.scales = 2.0 ** torch.arange(frequencies) * np.pi
            width = 3 + 6 * frequencies
            self.mlp = torch.nn.Sequential(
                torch.nn.Linear(width, hidden), torch.nn.ReLU(),
                torch.nn.Linear(hidden, hidden), torch.nn.ReLU(),
                torch.nn.Linear(hidden, 4))

        def forward(self, x):
            angles = (x[:, :, None] * self.scales).flatten(1)
            out = self.mlp(torch.cat([x, angles.sin(), angles.cos()], 1))
            return torch.sigmoid(out[:, :3]), torch.nn.functional.softplus(out[:, 3] - 1.0)
    return Field()


def main(argv=None):
    a = parse_args(argv)
    mi.set_variant(a.variant)
    import torch

    import mi_tetvr
    from mi_tetvr.camera import fibonacci_cameras
    from mi_tetvr.color import linear_to_srgb
    from mi_tetvr.interop import ray_renderer
    from mi_tetvr.mesh.generate import blob_field, grid_mesh
    from mi_tetvr.recon.metrics import psnr
    torch.manual_seed(0)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)

    # 1. the target volume and its photos
    V, T = grid_mesh(a.cells, jitter=0.15)
    color, opacity = blob_field(V, 2.0)
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "tetvr"},
                          "volume": mi_tetvr.tetmesh_dict(V, T, color, opacity)})
    keys = ["volume.vertex_color", "volume.vertex_opacity"]
    render = ray_renderer(scene, keys, "torch")
    cams = fibonacci_cameras(2 * a.views, radius=4.0, res=a.res)
    train, test = cams[0::2], cams[1::2][:4]

    def rays_of(cameras):
        o, d = zip(*(c.rays() for c in cameras))
        return (torch.tensor(np.concatenate(o), dtype=torch.float32),
                torch.tensor(np.concatenate(d), dtype=torch.float32))
    truth = {keys[0]: torch.tensor(color, dtype=torch.float32),
             keys[1]: torch.tensor(opacity, dtype=torch.float32)}
    o_train, d_train = rays_of(train)
    o_test, d_test = rays_of(test)
    with torch.no_grad():
        target = render(o_train, d_train, values=truth)
        target_test = render(o_test, d_test, values=truth)

    # 2. the network, and 3. its fit on random rays of all the photos
    field = network(torch)
    x = torch.tensor(V, dtype=torch.float32)
    opt = torch.optim.Adam(field.parameters(), lr=a.lr)
    losses = []
    t0 = time.perf_counter()
    for step in range(a.steps):
        pick = torch.randint(len(o_train), (a.rays,))
        c, s = field(x)
        rgba = render(o_train[pick], d_train[pick], values={keys[0]: c, keys[1]: s})
        loss = (rgba - target[pick]).square().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
        if not a.quiet and step % 50 == 0:
            print(f"step {step:4d}  loss {loss.item():.5f}")
    seconds = time.perf_counter() - t0

    # 4. held-out views
    def scores(values):
        with torch.no_grad():
            rgba = render(o_test, d_test, values=values).numpy()
        mse = np.mean((linear_to_srgb(np.clip(rgba[:, :3], 0, 1))
                       - linear_to_srgb(np.clip(target_test.numpy()[:, :3], 0, 1))) ** 2)
        return psnr(float(mse)), rgba
    with torch.no_grad():
        c0, s0 = network(torch)(x)
    start_psnr, _ = scores({keys[0]: c0, keys[1]: s0})
    with torch.no_grad():
        c, s = field(x)
    fitted_psnr, fitted = scores({keys[0]: c, keys[1]: s})
    if not a.quiet:
        print(f"{a.steps} steps in {seconds:.1f} s; held-out PSNR {fitted_psnr:.2f} dB "
              f"(the untrained network: {start_psnr:.2f} dB)")

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    n = a.res * a.res
    fig, ax = plt.subplots(1, 3, figsize=(11, 3.6))
    for axis, img, title in ((ax[0], target_test.numpy()[:n], "target (held out)"),
                             (ax[1], fitted[:n], f"network, {fitted_psnr:.1f} dB")):
        axis.imshow(linear_to_srgb(np.clip(img[:, :3], 0, 1)).reshape(a.res, a.res, 3))
        axis.set_title(title)
        axis.axis("off")
    ax[2].semilogy(losses)
    ax[2].set_xlabel("Adam step")
    ax[2].set_title(f"L2 loss, {a.rays} random rays a step")
    fig.tight_layout()
    picture = out / "torch_network.png"
    fig.savefig(picture, dpi=100)
    plt.close(fig)
    return {"losses": losses, "psnr": fitted_psnr, "start_psnr": start_psnr,
            "seconds": seconds, "files": {"picture": str(picture)},
            "torch": torch.__version__}


if __name__ == "__main__":
    main()
