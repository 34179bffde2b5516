"""The reference measurement in PyTorch on this machine: DrQ-v2's encoder (4 × 3×3 conv, 32
channels, ReLU, first stride 2) + a 64-wide trunk projection, forward and gradient w.r.t. the
parameters over uint8 images, best steady-state seconds of five — the same work as
``encoder_gradient_seconds`` in ``benchmarks/iteration.py``, for its PyTorch column.

    python benchmarks/pytorch_encoder.py [--images 512 --image-size 84 --channels 9]

Needs PyTorch (not a dependency of dva: install it beside, ``pip install torch``). Runs on one
thread so that it compares with one pinned core.
"""

from __future__ import annotations

import argparse
import time


def main() -> None:
    import torch

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--images", type=int, default=512)
    parser.add_argument("--image-size", type=int, default=84)
    parser.add_argument("--channels", type=int, default=9)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    layers: list[torch.nn.Module] = []
    channels = args.channels
    for stride in (2, 1, 1, 1):
        layers += [torch.nn.Conv2d(channels, 32, 3, stride=stride), torch.nn.ReLU()]
        channels = 32
    encoder = torch.nn.Sequential(*layers, torch.nn.Flatten())
    pixels = torch.randint(0, 256, (args.images, args.channels, args.image_size, args.image_size), dtype=torch.uint8)
    features = encoder(pixels[:1].float()).shape[-1]
    projection = torch.nn.Linear(features, 64)
    params = list(encoder.parameters()) + list(projection.parameters())

    def step() -> None:
        loss = torch.tanh(projection(encoder(pixels.float() / 255.0 - 0.5))).sum()
        torch.autograd.grad(loss, params)

    step()
    times = []
    for _ in range(5):
        start = time.perf_counter()
        step()
        times.append(time.perf_counter() - start)
    print(
        f"PyTorch {torch.__version__}, {args.threads} thread(s): encoder + trunk forward + parameter gradient over "
        f"{args.images} × {args.image_size}² × {args.channels}: {min(times):.3f} s (best of 5)"
    )


if __name__ == "__main__":
    main()
