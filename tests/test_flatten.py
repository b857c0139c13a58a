"""Struct parameters compiled as flat array parameters (``kernels/flatten.py``)."""

import functools

import numpy as np
import pytest
import warp as wp

from warpspring.kernels.flatten import flat_inputs, flat_kernel, flat_launch


@wp.struct
class Leaf:
    values: wp.array[float]
    count: int


@wp.struct
class Tree:
    leaf: Leaf
    table: wp.array2d[float]


OFFSET = 1000.0  # a module global the kernel reads


@functools.cache
def tree_kernel(scale: float, last: tuple = ()):
    """A factory kernel reading a nested struct, a factory local (its annotation type too) and a global."""
    dtype = wp.float32

    @flat_kernel(module="unique", enable_backward=False, last=last)
    def total(n: int, tree: Tree, extra: wp.array[dtype], out: wp.array[dtype]):
        i = wp.tid()
        out[i] = tree.leaf.values[i] * scale + tree.table[1, i] + float(tree.leaf.count) + extra[i] + float(n) + OFFSET

    return total


LABELS = {
    (): ["n", "tree__leaf__values", "tree__leaf__count", "tree__table", "extra", "out"],
    # Leaves named in ``last`` (a whole sub-struct by its prefix, or one leaf) follow every other parameter,
    # outputs included; they are still passed and read.
    ("tree__leaf", "tree__table"): ["n", "extra", "out", "tree__leaf__values", "tree__leaf__count", "tree__table"],
    ("tree__leaf__count",): ["n", "tree__leaf__values", "tree__table", "extra", "out", "tree__leaf__count"],
}


@pytest.mark.parametrize("last", list(LABELS), ids=lambda last: "+".join(last) or "declared")
def test_flat_kernel_rebuilds_nested_structs(device, last):
    """The flattened kernel has one parameter per leaf field, in declaration order but for the leaves named
    in ``last``, and computes what the struct-parameter kernel would: every leaf reaches the body through the
    rebuilt struct, wherever it sits in the parameter list."""
    kernel = tree_kernel(2.0, last)
    assert [a.label for a in kernel.adj.args] == LABELS[last]
    leaf = Leaf()
    leaf.values = wp.array(np.arange(4.0), dtype=float, device=device)
    leaf.count = 10
    tree = Tree()
    tree.leaf = leaf
    tree.table = wp.array(np.arange(8.0).reshape(2, 4), dtype=float, device=device)
    extra = wp.full(4, 0.5, dtype=float, device=device)
    out = wp.zeros(4, dtype=float, device=device)
    arguments = flat_inputs([3, tree, extra])
    assert arguments[0] == 3 and arguments[2] == 10 and arguments[-1] is extra
    flat_launch(kernel, dim=4, inputs=[3, tree, extra], outputs=[out], device=device)
    i = np.arange(4.0)
    np.testing.assert_array_equal(out.numpy(), i * 2.0 + (4.0 + i) + 10.0 + 0.5 + 3.0 + OFFSET)


def test_flat_kernel_without_structs_is_a_plain_kernel():
    def plain(x: wp.array[float]):
        x[wp.tid()] = 1.0

    kernel = flat_kernel(plain, module="unique", enable_backward=False)
    assert [a.label for a in kernel.adj.args] == ["x"]
