"""A vector gather of bytes for the compiled renderer: 16 table lookups in one instruction where the CPU has one.

`gather_bytes(table, index, first, out, start)` sets ``out[start + i] = table[index[first + i]]`` for i in
0..15. Numba's
loop vectoriser leaves a byte lookup scalar (a load, a sign fix-up and a store per byte); this emits LLVM's
``llvm.masked.gather`` of 16 dwords at the byte offsets and keeps their low bytes: one ``vpgatherdd`` with
AVX-512 (two with AVX2); LLVM turns it into scalar loads on CPUs without gathers. Each lookup reads the
three bytes after its own too, so the table must have three bytes to spare at its end (`GATHER_PAD`).
"""
from __future__ import annotations

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

LANES = 16  # lookups per gather_bytes
GATHER_PAD = 3  # bytes read past the last index


@intrinsic
def gather_bytes(typingctx, table, index, first, out, start):
    """out[start:start + 16] = table[index[first:first + 16]]: table and out contiguous uint8 arrays, index a
    contiguous int32 array of offsets into table; neither bounds nor offsets are checked, and table must be
    padded by `GATHER_PAD` bytes."""
    arrays = (table, index, out)
    if not (all(isinstance(a, types.Array) and a.layout == "C" for a in arrays) and table.dtype == types.uint8
            and out.dtype == types.uint8 and index.dtype == types.int32
            and isinstance(first, types.Integer) and isinstance(start, types.Integer)):
        return None

    def codegen(context, builder, signature, args):
        table_data = context.make_array(signature.args[0])(context, builder, args[0]).data
        index_data = context.make_array(signature.args[1])(context, builder, args[1]).data
        out_data = context.make_array(signature.args[3])(context, builder, args[3]).data
        byte, dword, flag = ir.IntType(8), ir.IntType(32), ir.IntType(1)
        dwords = ir.VectorType(dword, LANES)
        first_offset = builder.gep(index_data, [args[2]])
        offsets = builder.load(builder.bitcast(first_offset, dwords.as_pointer()), align=4)
        # a vector GEP (table + offsets), which llvmlite's builder does not spell: its type set by hand
        pointers = ir.instructions.GEPInstr(builder.block, table_data, [offsets], True, "", source_etype=byte)
        pointers.type = ir.VectorType(byte.as_pointer(), LANES)
        builder._insert(pointers)
        dword_pointers = builder.bitcast(pointers, ir.VectorType(dword.as_pointer(), LANES))
        gather_type = ir.FunctionType(dwords, [dword_pointers.type, dword, ir.VectorType(flag, LANES), dwords])
        gather = cgutils.get_or_insert_function(builder.module, gather_type,
                                                f"llvm.masked.gather.v{LANES}i32.v{LANES}p0i32")
        every = ir.Constant(ir.VectorType(flag, LANES), [1] * LANES)
        values = builder.call(gather, [dword_pointers, ir.Constant(dword, 1), every, ir.Constant(dwords, None)])
        target = builder.gep(out_data, [args[4]])
        builder.store(builder.trunc(values, ir.VectorType(byte, LANES)),
                      builder.bitcast(target, ir.VectorType(byte, LANES).as_pointer()), align=1)
        return context.get_dummy_value()

    return types.void(table, index, first, out, start), codegen
