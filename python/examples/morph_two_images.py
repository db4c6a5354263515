"""Morph two images and look at the result: frames, the energy per sweep, and det J of the
composed map (where the path compresses or stretches A on its way to B).

    pip install ./python matplotlib
    python python/examples/morph_two_images.py a.png b.png      # or no arguments: two discs

Without matplotlib it prints the numbers and saves the morph only.
"""

import sys

import numpy as np

import deepmorph


def two_discs(side=96):
    """A red disc that moves and grows into a larger one: a pair with an obvious transport."""
    yy, xx = np.mgrid[0:side, 0:side].astype(np.float32)

    def disc(cy, cx, r):
        alpha = np.clip(r + 1 - np.hypot(yy - cy, xx - cx), 0, 1)[..., None]
        return (alpha * np.array([0.9, 0.2, 0.1], np.float32)).astype(np.float32)

    return disc(40, 38, 16), disc(54, 58, 20)


def det_jacobian(phi):
    """det of the Jacobian of a map [2, H, W] (rows, columns), central differences."""
    d_rows = np.gradient(phi[0])  # d phi0 / d row, d phi0 / d col
    d_cols = np.gradient(phi[1])
    return d_rows[0] * d_cols[1] - d_rows[1] * d_cols[0]


def main():
    a, b = (sys.argv[1], sys.argv[2]) if len(sys.argv) == 3 else two_discs()
    # The discs sit apart: from the identity the path would mostly cross-fade; a similarity
    # found from the images (SPEC §11) starts it with the transport instead.
    m = deepmorph.morph(a, b, K=8, levels=3, sweeps=60, size=128, align="similarity", progress=True)
    print(m)
    print("\n".join(m.notes))
    print("final energy", m.energy["E"][-1], "| data share", m.metrics["levels"][-1]["data_share"])
    folder = m.save("morph-out", force=True)
    print("saved to", folder, "(deepmorph eval", folder, "measures it again)")

    det = det_jacobian(m.composed)
    print(f"det J of the composed map: min {det.min():.3f}, max {det.max():.3f}")
    try:
        import matplotlib.pyplot as plt
    except ImportError:
        return
    frames = deepmorph.inbetween(m, 17)
    fig, axes = plt.subplots(2, 5, figsize=(14, 6))
    for ax, j in zip(axes[0], np.linspace(0, len(frames) - 1, 5).astype(int)):
        ax.imshow(frames[j])
        ax.set_title(f"t = {j / (len(frames) - 1):.2f}")
        ax.axis("off")
    axes[1, 0].semilogy(m.energy["E"])
    axes[1, 0].set_title("E per sweep (all levels)")
    shown = axes[1, 1].imshow(det, cmap="coolwarm", vmin=0, vmax=2)
    axes[1, 1].set_title("det J of the composed map")
    fig.colorbar(shown, ax=axes[1, 1])
    step = max(1, m.composed.shape[1] // 16)
    rows, cols = np.mgrid[0 : m.composed.shape[1] : step, 0 : m.composed.shape[2] : step]
    disp = m.composed[:, ::step, ::step] - np.stack([rows, cols])
    axes[1, 2].imshow(m.frames[0])
    axes[1, 2].quiver(cols, rows, disp[1], disp[0], color="w", angles="xy", scale_units="xy", scale=1)
    axes[1, 2].set_title("where A's pixels go")
    for ax in axes[1, 3:]:
        ax.axis("off")
    fig.tight_layout()
    fig.savefig("morph-out/overview.png", dpi=80)
    print("plot: morph-out/overview.png")


if __name__ == "__main__":
    main()
