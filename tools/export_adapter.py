#!/usr/bin/env python
"""Export a diffusion or structured checkpoint's prepared adapter to one AOTInductor package for C++ (and Python)
controllers.

    python tools/export_adapter.py --ckpt CKPT --out runs/adapter.pt2 [--steps 20] [--batch-sizes dynamic|N]
        [--seeds 0,1,2]

One package serves every fault set (faults are inputs); see README "Deploy in a C++ controller" and
``lightning_bodyschema.deploy``. ``--steps`` and ``--seeds`` are the diffusion sampler's. Compiling needs a C++
compiler and takes minutes on 2 cores. The file is written atomically; its SHA-256 is printed (pin it when loading:
a package runs compiled code). Bad input exits with code 2 and one line on stderr.
"""
import time
import warnings

from lightning_bodyschema.apps.common import (argument_parser, check_out, exits_cleanly, load_checked_schema,
                                              torch_one_thread)
from lightning_bodyschema.errors import BodySchemaInputError


def _seeds(text: str) -> list:
    try:
        return [int(s) for s in text.split(",")]
    except ValueError:
        raise BodySchemaInputError(f"--seeds {text!r}: give integers separated by commas, e.g. 0,1,2") from None


@exits_cleanly
def main(argv=None):
    parser = argument_parser("Export the prepared diffusion or structured adapter (faults as inputs) to one "
                             "AOTInductor .pt2 package with its metadata.", checkpoint=True)
    parser.add_argument("--ckpt", required=True, help="trained diffusion or structured schema checkpoint (.ckpt)")
    parser.add_argument("--out", required=True, help="package to write (.pt2), atomically")
    parser.add_argument("--steps", type=int, default=20, help="diffusion: strided denoising steps (default 20)")
    parser.add_argument("--batch-sizes", default="dynamic",
                        help="'dynamic' (1..4096 cases per call, default) or one static batch size, e.g. 1")
    parser.add_argument("--seeds", default=None,
                        help="diffusion: x_T draws the package may pick by its seed input (default: the schema's "
                        "sample_seed)")
    args = parser.parse_args(argv)
    # torch's note that its pytree LeafSpec is deprecated, raised as Lightning's and torch.export's specs are copied
    warnings.filterwarnings("ignore", message=".*LeafSpec.*", category=FutureWarning)
    from lightning_bodyschema.deploy.package import export_package, file_sha256, parse_batch
    from lightning_bodyschema.schemas import StructuredSchema

    if not args.out.endswith(".pt2"):
        raise BodySchemaInputError(f"--out {args.out!r}: an AOTInductor package ends in .pt2")
    check_out(args.out, args.ckpt)
    batch = parse_batch(args.batch_sizes)
    seeds = None if args.seeds is None else _seeds(args.seeds)
    torch_one_thread()
    schema = load_checked_schema(args)
    from lightning_bodyschema.deploy.module import check_supported

    check_supported(schema)
    structured = isinstance(schema, StructuredSchema)
    if structured and seeds is not None:
        raise BodySchemaInputError("--seeds: the structured schema draws nothing; export it without --seeds")
    if not structured and not 1 <= args.steps <= schema.schedule.n_timesteps:
        raise BodySchemaInputError(f"--steps {args.steps}: must be in 1..{schema.schedule.n_timesteps}")
    if seeds is not None:  # the schema's own draw first: the package's default seed
        seeds = [int(schema.hparams.sample_seed)] + [s for s in seeds if s != int(schema.hparams.sample_seed)]
    print("exporting: torch.export traces the adapter, then AOTInductor compiles it to C++ (several minutes on 2 "
          "cores; it prints the package's path when done)", flush=True)
    start = time.perf_counter()
    export_package(schema, args.out, args.steps, batch, file_sha256(args.ckpt), seeds)
    what = "structured" if structured else f"diffusion, {args.steps} steps"
    print(f"wrote {args.out} ({type(schema).__name__}: {what}, batch {batch}) in {time.perf_counter() - start:.0f} s")
    print(f"sha256 {file_sha256(args.out)}  (pin it: load_exported(path, expected_sha256=...), --sha256 in C++)")


if __name__ == "__main__":
    main()
