"""Diagnostic of docs/transfer.md: does the network fail on photographs because its BatchNorm
statistics are the synthetic images'? Test-time BatchNorm adaptation (AdaBN, Li et al. 2016): every
BatchNorm layer's statistics recomputed from the photographs' own crops (the 25 scored people and
their mirror images; transductive, as AdaBN is) or, as a control, from 50 synthetic crops, then the
transfer check's PCK@0.1 on both domains.

    python experiments/transfer/transfer_adabn.py [CHECKPOINT] [--check out/transfer/check/base]

Uses the reference answers cached by an earlier ``recovery transfer`` run in ``--check`` (no new
MediaPipe calls), the development set ``out/transfer_dev`` and the test set ``out/data/test``.
"""

from __future__ import annotations

import argparse
import copy
from pathlib import Path

import torch

from recovery.eval import transfer as T
from recovery.predictor import load_predictor


def adapted(pr, crops: list[torch.Tensor]):
    """A copy of predictor ``pr`` whose BatchNorm statistics are those of ``crops`` and their mirrors."""
    out = copy.copy(pr)
    out.model = copy.deepcopy(pr.model)
    for m in out.model.modules():
        if isinstance(m, torch.nn.modules.batchnorm._BatchNorm):
            m.reset_running_stats()
            m.momentum = None  # the plain average over the one batch
            m.train()
    with torch.no_grad():
        x = torch.stack(crops)
        out.model(torch.cat([x, x.flip(-1)]))
    out.model.eval()
    return out


def pck(d) -> float:
    return T.pck_share(d.counts(0.1), "ours")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("checkpoint", nargs="?", default="default")
    ap.add_argument("--check", type=Path, default=Path("out/transfer/check/base"))
    args = ap.parse_args()
    command = T.reference_command(None)
    pr = load_predictor(args.checkpoint)
    real = T.read_boxes(Path("out/transfer_dev"))
    syn = T.synthetic_people(Path("out/data/test"), args.check / "synthetic_images", 400)
    d_real, v_real = T.score_domain("real", real, command, args.check, pr)
    d_syn, v_syn = T.score_domain("synthetic", syn, command, args.check, pr)
    print("| BatchNorm statistics | PCK@0.1 photographs | PCK@0.1 synthetic | ratio (photographs as scored, synthetic as is) |")
    print("|---|---:|---:|---:|")
    print(f"| as trained | {100 * pck(d_real):.1f} % | {100 * pck(d_syn):.1f} % | {T.summarise(d_real, d_syn)['transfer_ratio@0.1']:.2f} |")
    to_tensor = lambda v: torch.from_numpy(v["crop"]).permute(2, 0, 1).float() / 255  # noqa: E731
    for label, crops in ((f"the photographs' {len(v_real)} crops", [to_tensor(v) for v in v_real]),
                         ("50 synthetic crops", [to_tensor(v) for v in v_syn[:50]])):
        p2 = adapted(pr, crops)
        dr, _ = T.score_domain("real", real, command, args.check, p2)
        ds, _ = T.score_domain("synthetic", syn, command, args.check, p2)
        print(f"| from {label} | {100 * pck(dr):.1f} % | {100 * pck(ds):.1f} % | {T.summarise(dr, d_syn)['transfer_ratio@0.1']:.2f} |")


if __name__ == "__main__":
    main()
