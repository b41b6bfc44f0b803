"""A process of a training run of 2 gloo processes, launched as ``torchrun`` would.

Its own module (it imports no fixtures), so that the processes that
``torch.multiprocessing.spawn`` starts can import it.
"""

from __future__ import annotations

from pathlib import Path

import torch


def direct_process(rank: int, port: int, config: str, out: str, stop_after: int) -> None:
    """Process ``rank`` of 2 launched as torchrun would, stopped after ``stop_after`` steps."""
    import os

    from freipose.io.labels import read_labels_h5
    from freipose.nn.config import load_config
    from freipose.nn.dataset import MultiViewDataset
    from freipose.nn.train import train_pose
    from freipose.skeleton import Skeleton

    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), RANK=str(rank),
                      WORLD_SIZE="2")  # fmt: skip
    torch.set_num_threads(1)
    labels_path = Path(config).parent / "data" / "labels.h5"
    labels = read_labels_h5(labels_path)
    source = MultiViewDataset(labels, root=labels_path.parent)
    try:
        train_pose(load_config(config), out, source, Skeleton("labels", labels.keypoints),
                   progress=False, stop_after=stop_after)  # fmt: skip
    finally:
        torch.distributed.destroy_process_group()
