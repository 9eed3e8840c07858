"""``blsm reparam MODEL NEW_TEMPLATE --out MODEL2``: a BLSM model in another topology (thesis ch. 3).

    blsm reparam default my_template.obj --out model2.npz
    blsm reparam default --subdivide 1 --out model_loop1.npz --write-template loop1.obj

``MODEL`` is a model file or ``default`` (the packaged model). The new template is an OBJ / PLY mesh
or, with ``--subdivide N``, the model's own template subdivided N times (``--scheme loop``, the
subdivision surface, or ``midpoint``). Bad input is one line ``blsm reparam: error: ...`` naming the
file on stderr, exit status 2, and no output file. The method is :mod:`blsm.learn.reparam.model`.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path
from typing import Any


def add_parser(sub: Any, help_text: str, wrap: Callable) -> None:
    """Add ``blsm reparam`` to ``blsm``'s sub-commands (``help_text``: its line in ``blsm --help``;
    ``wrap(name, run)``: the handler that turns a ValueError into one line and exit 2)."""
    p = sub.add_parser(
        "reparam", help=help_text,
        description="Reparameterise a BLSM model to a new template (thesis ch. 3): vertex-to-surface "
                    "correspondences W (Sec. 3.3.2), shape space (Eq. 3.5), bone correctives (Eq. 3.6), "
                    "blend weights (Eq. 3.7); joints and keypoints carried over. See docs/reparam.md.",
    )  # fmt: skip
    p.add_argument("model", help="model file (.npz), or 'default' for the packaged model")
    p.add_argument("template", nargs="?", type=Path, default=None,
                   help="new template mesh (OBJ / PLY), in the model's frame (metres, Y up)")
    p.add_argument("--out", type=Path, required=True, help="the reparameterised model file (.npz)")
    p.add_argument("--subdivide", type=int, default=0, metavar="N",
                   help="instead of a template file: the model's template subdivided N times")
    p.add_argument("--scheme", choices=("loop", "midpoint"), default="loop", help="subdivision scheme (default loop)")
    p.add_argument("--write-template", type=Path, default=None, metavar="OBJ",
                   help="also write the (aligned) new template as an OBJ")
    p.add_argument("--align", choices=("auto", "none", "rigid", "similarity"), default="auto",
                   help="alignment of the template to the model's surface (default auto: none when "
                        "within 5 mm on average, else rigid ICP)")
    p.add_argument("--shape-space", choices=("mapped", "eq35"), default="mapped",
                   help="mapped: W P_s, coefficients keep their meaning (default); eq35: the K+1 "
                        "principal components of Eq. 3.5")
    p.add_argument("--far-mm", type=float, default=10.0,
                   help="a correspondence farther than this (mm) counts as not covering (default 10)")
    p.add_argument("--far-fraction", type=float, default=0.01,
                   help="largest allowed fraction of far vertices, either way (default 0.01)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output file")
    p.set_defaults(func=wrap("reparam", _run))


def _run(args: argparse.Namespace) -> int:
    from blsm import io
    from blsm.learn.reparam.model import ReparamConfig, read_template, reparameterise, subdivide_template
    from blsm.model import DEFAULT_MODEL, load

    if args.out.exists() and not args.overwrite:
        raise ValueError(f"{args.out}: exists (use --overwrite to replace it)")
    if (args.template is None) == (args.subdivide == 0):
        raise ValueError("give a NEW_TEMPLATE file or --subdivide N (one of the two)")
    model_path = DEFAULT_MODEL if args.model in ("default", "packaged") else Path(args.model)
    data = io.read_model(model_path)
    if args.template is not None:
        v, f = read_template(args.template)
        where = str(args.template)
    else:
        v, f = subdivide_template(data.arrays["template"], data.arrays["faces"], args.subdivide, args.scheme)
        where = f"{model_path} subdivided ({args.scheme}, {args.subdivide})"
    cfg = ReparamConfig(align=args.align, shape_space=args.shape_space, far_distance=args.far_mm / 1000.0,
                        far_fraction=args.far_fraction, uncovered_fraction=args.far_fraction)
    new, report = reparameterise(data, v, f, cfg, where)
    io.save_model(new, args.out)
    load(args.out)  # what was written loads as a model
    if args.write_template is not None:
        _write_obj(args.write_template, new.arrays["template"], new.arrays["faces"])
    cov = report["coverage"]
    print(f"wrote {args.out}: {len(v)} vertices (from {len(data.arrays['template'])}), alignment "
          f"{report['alignment']['mode']}, new->old {cov['new_to_old_mm']['mean']:.3f} mm mean "
          f"({cov['new_to_old_mm']['max']:.2f} max), old->new {cov['old_to_new_mm']['mean']:.3f} mm mean, "
          f"{100 * cov['coincident_fraction']:.1f} % of vertices within 0.1 mm of the old surface")
    return 0


def _write_obj(path: Path, vertices, faces) -> None:
    from blsm.io import atomic_write

    with atomic_write(path, "w") as fh:
        fh.write("".join(f"v {x:.7f} {y:.7f} {z:.7f}\n" for x, y, z in vertices))
        fh.write("".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in faces))
