"""deploy.products: an exported program's small float64 products as multiply-sums (no compile): the same numbers to
the roundings of a sum, inside a torch.while_loop too; float32, large and symbolic-size products left to the BLAS."""
import torch
from physics_checks import rounding_tol

from lightning_bodyschema.deploy.products import PRODUCTS, SMALL_PRODUCT, fuse_small_products

M, N = 50, 7  # a Newton system's tensions and joints


class Products(torch.nn.Module):
    """Every product kind a package's graph holds (bmm, baddbmm with alpha -1, addmm, 2-D @ 3-D), one in a
    while_loop's body, a float32 one and one above SMALL_PRODUCT."""

    def __init__(self):
        super().__init__()
        gen = torch.Generator().manual_seed(0)
        self.register_buffer("W", torch.randn(N, 38, generator=gen, dtype=torch.float64))
        self.register_buffer("bias", torch.randn(38, generator=gen, dtype=torch.float64))
        self.register_buffer("big", torch.randn(64, 128, generator=gen, dtype=torch.float64))  # 64 128 129 > limit
        self.register_buffer("W32", self.W.float())

    def forward(self, G, lam, f_ref, wide):
        free_f = torch.baddbmm(f_ref.unsqueeze(-1), G, lam.unsqueeze(-1), alpha=-1.0).squeeze(-1)  # (B, M)
        gram = torch.bmm(G.transpose(1, 2), G)  # (B, N, N)

        def body(k, v):
            return k + 1, torch.bmm(gram, v) / (1.0 + M)

        _, power = torch.while_loop(lambda k, v: k < 3, body, (torch.zeros((), dtype=torch.int64), lam.unsqueeze(-1)))
        rows = torch.addmm(self.bias, lam, self.W) + (self.W.unsqueeze(0).transpose(1, 2) @ G.transpose(1, 2)[..., :1])[..., 0]
        return free_f, power.squeeze(-1), rows, self.big @ wide, (lam.float() @ self.W32).double()


def _inputs(batch: int):
    gen = torch.Generator().manual_seed(1)
    return (torch.randn(batch, M, N, generator=gen, dtype=torch.float64),
            torch.randn(batch, N, generator=gen, dtype=torch.float64),
            torch.randn(batch, M, generator=gen, dtype=torch.float64),
            torch.randn(128, 129, generator=gen, dtype=torch.float64))


def _products_left(program) -> list:
    return [str(node.target) for module in program.graph_module.modules() if isinstance(module, torch.fx.GraphModule)
            for node in module.graph.nodes if node.op == "call_function" and node.target in PRODUCTS]


def test_small_float64_products_become_multiply_sums_with_the_same_numbers():
    module, inputs = Products(), _inputs(1)
    program = fuse_small_products(torch.export.export(module, inputs, strict=False))
    assert 64 * 128 * 129 > SMALL_PRODUCT
    assert sorted(_products_left(program)) == ["aten.matmul.default"] * 2  # the large one and the float32 one
    with torch.no_grad():
        got, want = program.module()(*inputs), module(*inputs)
    for g, w in zip(got, want):
        # a sum of M products of unit-scale normals (three nested for the power iteration), in another order
        scale = float(w.abs().max()) + M * float(max(x.abs().max() for x in inputs))
        torch.testing.assert_close(g, w, rtol=0, atol=rounding_tol(4 * M, scale))
    assert not torch.equal(got[0], -got[0])  # the numbers are there (a dropped term would be off by O(1))


def test_a_dynamic_batch_keeps_its_blas_products():
    """Symbolic sizes stay the BLAS's (AOTInductor's loops over a symbolic size measured slower)."""
    inputs = _inputs(2)
    batch = torch.export.Dim("batch", min=1, max=64)
    program = torch.export.export(Products(), inputs, dynamic_shapes=({0: batch}, {0: batch}, {0: batch}, None),
                                  strict=False)
    before = _products_left(program)
    assert sorted(_products_left(fuse_small_products(program))) == sorted(before) and len(before) >= 6
