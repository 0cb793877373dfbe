"""The exported program's small float64 matrix products as broadcast multiply-sums, which AOTInductor fuses into the
loops around them.

At a few cases per call every product of a package is small (the Newton systems' 7 x 50 Jacobians, the gravity
tree's 4 x 4 poses, the per-muscle body's 43 x 1273 coefficients times its 1273 x 8 basis at most), and AOTInductor
otherwise calls the BLAS for each one: a call, an output allocation and the BLAS's small-matrix path every time.
``a @ b`` written as ``(a[..., :, :, None] * b[..., None, :, :]).sum(-2)`` is the same product summed in another
order (float64 roundings), and the compiler makes it a loop of the kernel that produces or uses it.

A product stays a BLAS call where a size is symbolic (a dynamic batch's program: AOTInductor's loops over a
symbolic size made the myoArm package slower, not faster), where ``m k n`` exceeds ``SMALL_PRODUCT`` (there the BLAS
is the faster: the crossover is in BENCHMARKS.md, "Deploy: exported adapter tail latency"), or where it is not
float64 (a float32 network keeps its kernels' roundings).

The program's graphs are edited in place (``torch.cond`` and ``torch.while_loop`` branches included), not traced
again: ``ExportedProgram.run_decompositions`` would, and AOTInductor then fails to lower a dynamic batch's program.
"""
from __future__ import annotations

import torch
from torch._guards import detect_fake_mode
from torch.fx.experimental.symbolic_shapes import is_concrete_int

aten = torch.ops.aten

SMALL_PRODUCT = 1 << 20  # the largest m * k * n written as a multiply-sum

# op -> (positions of the two factors, position of the added term or None) in its arguments
PRODUCTS = {aten.matmul.default: (0, 1, None), aten.mm.default: (0, 1, None), aten.bmm.default: (0, 1, None),
            aten.addmm.default: (1, 2, 0), aten.baddbmm.default: (1, 2, 0)}


def is_small(a, b) -> bool:
    """Whether ``a (..., m, k) @ b (..., k, n)`` (tensors or fake tensors) is a product to fuse (module docstring)."""
    if a.dim() < 2 or b.dim() < 2 or a.dtype != torch.float64 or b.dtype != torch.float64:
        return False
    if not all(is_concrete_int(size) for size in (*a.shape, *b.shape)):
        return False
    return int(a.shape[-2]) * int(a.shape[-1]) * int(b.shape[-1]) <= SMALL_PRODUCT


def fuse_small_products(program):
    """``program`` (a ``torch.export.ExportedProgram``) with its small products rewritten in place (module
    docstring); returns it."""
    for graph_module in program.graph_module.modules():
        if isinstance(graph_module, torch.fx.GraphModule):
            rewritten = [_rewrite(graph_module.graph, node) for node in list(graph_module.graph.nodes)
                         if node.op == "call_function" and node.target in PRODUCTS]
            if any(rewritten):
                graph_module.recompile()
    return program


def _rewrite(graph, node) -> bool:
    """Replace the product ``node`` (``beta added + alpha a @ b`` for addmm, baddbmm) by its multiply-sum where
    ``is_small`` and it is not an output of the graph (whose name the program's signature holds); whether it did."""
    first, second, added = PRODUCTS[node.target]
    a, b = node.args[first], node.args[second]
    if any(user.op == "output" for user in node.users) or not is_small(a.meta["val"], b.meta["val"]):
        return False
    beta, alpha = node.kwargs.get("beta", 1), node.kwargs.get("alpha", 1)
    with graph.inserting_before(node):
        emit = _emitter(graph, node)
        out = emit(aten.sum.dim_IntList, emit(aten.mul.Tensor, emit(aten.unsqueeze.default, a, -1),
                                              emit(aten.unsqueeze.default, b, -3)), [-2])
        out = out if alpha == 1 else emit(aten.mul.Tensor, out, alpha)
        if added is not None and beta != 0:  # beta 0: the added term is ignored, NaN included
            term = node.args[added]
            out = emit(aten.add.Tensor, out, term if beta == 1 else emit(aten.mul.Tensor, term, beta))
    node.replace_all_uses_with(out)
    graph.erase_node(node)
    return True


_VALUES = ("val", "tensor_meta", "example_value")  # what describes the product's own output, not its provenance


def _emitter(graph, node):
    """``emit(op, *args)``: a new node of ``graph`` with ``node``'s provenance and its fake value (what later passes
    and the compiler read)."""
    fake_mode = detect_fake_mode([node.meta["val"]])

    def emit(op, *args):
        new = graph.call_function(op, args)
        new.meta.update({key: value for key, value in node.meta.items() if key not in _VALUES})
        values = [arg.meta["val"] if isinstance(arg, torch.fx.Node) else arg for arg in args]
        with fake_mode:
            new.meta["val"] = op(*values)
        return new
    return emit
