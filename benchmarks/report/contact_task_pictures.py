"""Pictures of the two contact tasks for docs/tasks.md: PushRetraction's task camera at the
start and once the scripted paddle has lifted the lobe off the target; GallbladderDissection's
at the start and once the scripted hook has freed the neck and the grasper has folded the
sac back to the critical view (both ducts exposed). Writes docs/img/contact_tasks.png.

    python benchmarks/report/contact_task_pictures.py
"""

from __future__ import annotations

import heml_gym.envs  # noqa: F401  (registers the envs)
from heml_gym.benchmarks.common import IMAGES, parse_arguments
from heml_gym.benchmarks.report.new_task_pictures import views


def main() -> int:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 2, figsize=(8, 6.4))
    start, end, info = views("heml_gym/PushRetraction-v0", lambda i: i["exposure"] >= 0.8, settle=3)
    axes[0, 0].imshow(start)
    axes[0, 0].set_title("PushRetraction: a paddle, no grasp\nstart: the blade on the floor, the target hidden",
                         fontsize=8, loc="left")
    axes[0, 1].imshow(end)
    axes[0, 1].set_title(f"lifted from beneath: {info['exposure']:.0%} exposed, "
                         f"{info['paddle_contact_pressure'] / 1e3:.1f} kPa on the lobe", fontsize=8, loc="left")
    start, end, info = views("heml_gym/GallbladderDissection-v0", lambda i: i["exposure"] >= 0.8, settle=3)
    axes[1, 0].imshow(start)
    axes[1, 0].set_title("GallbladderDissection: a grasper on the fundus, a hook beneath\nstart: the neck "
                         "stuck to its bed over the ducts", fontsize=8, loc="left")
    axes[1, 1].imshow(end)
    axes[1, 1].set_title(f"critical view: {info['released_fraction']:.0%} of the lower third freed,\n"
                         f"ducts {info['duct_exposure']:.0%} and {info['artery_exposure']:.0%} exposed",
                         fontsize=8, loc="left")
    for ax in axes.ravel():
        ax.set_axis_off()
    fig.tight_layout()
    IMAGES.mkdir(parents=True, exist_ok=True)
    fig.savefig(IMAGES / "contact_tasks.png", dpi=100)
    print(IMAGES / "contact_tasks.png")
    return 0


if __name__ == "__main__":
    parse_arguments(__doc__)
    raise SystemExit(main())
