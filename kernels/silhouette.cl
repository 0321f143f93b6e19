// Silhouette bits and block tables from uint8 masks (nodes/common/silhouettes.py:SilhouetteBits):
//   pack_block_rows  one bit per pixel (rows of ceil(W/8) bytes, a multiply trick on 8 bytes at once; pixel inside
//                    when value > 127, i.e. its top bit, or with ``opaque`` when value == 255) and the 8x8 pixel block
//                    counts prefixed along each block row, in one read of the mask;
//   block_cols       the prefix down the columns: a summed-area table of 8x8 pixel blocks.
// key.cl:chroma_key_bits writes the same layout straight from camera images and then runs block_cols too.
// NumPy references: nodes/common/silhouettes.py (SilhouetteBits.masks, block_table_reference).
#include "silhouette.h"

// 8 mask pixels (bytes) to one byte of bits, pixel x0 + i in bit i: inside when > 127 (the byte's top bit), or
// with ``opaque`` when 255 (its complement's byte is 0: ((c & 0x7F) + 0x7F) | c has its top bit clear exactly then)
inline uchar pack8(__global const uchar* p, int n, int opaque)
{
    if (n >= 8) {
        ulong v = as_ulong(vload8(0, p));
        if (opaque) {
            ulong c = ~v;
            v = ~((((c & 0x7F7F7F7F7F7F7F7FUL) + 0x7F7F7F7F7F7F7F7FUL) | c));
        }
        return (uchar)((((v >> 7) & 0x0101010101010101UL) * 0x0102040810204080UL) >> 56);
    }
    uchar b = 0;
    for (int i = 0; i < n; i++) b |= (uchar)((opaque ? p[i] == 255 : p[i] >> 7) << i);
    return b;
}

// One work-item per table row `by` of one view: packs the 8 mask rows of block row by - 1 into bits (rows of
// Wb bytes) and writes their block counts prefixed along the row. Table rows have Wb+1 entries with a zero
// first column; the table has Hb+1 rows with a zero first row. Reads the mask once, row by row.
__kernel void pack_block_rows(__global const uchar* mask, int W, int H, int opaque, __global uchar* bits,
                              int bit_off, __global int* sat, int sat_off)
{
    int by = get_global_id(0);
    int Wb = (W + 7) >> 3, Hb = (H + 7) >> 3;
    if (by > Hb) return;
    __global int* row = sat + sat_off + by * (Wb + 1);
    row[0] = 0;
    if (by == 0) {
        for (int bx = 0; bx < Wb; bx++) row[bx + 1] = 0;
        return;
    }
    int y0 = (by - 1) << 3, y1 = min(y0 + 8, H);
    for (int bx = 0; bx < Wb; bx++) row[bx + 1] = 0;
    for (int y = y0; y < y1; y++) {
        __global const uchar* m = mask + (size_t)y * W;
        __global uchar* b = bits + bit_off + (size_t)y * Wb;
        for (int bx = 0; bx < Wb; bx++) {
            uchar v = pack8(m + (bx << 3), W - (bx << 3), opaque);
            b[bx] = v;
            row[bx + 1] += popcount(v);
        }
    }
    int acc = 0;
    for (int bx = 1; bx <= Wb; bx++) {
        acc += row[bx];
        row[bx] = acc;
    }
}

// One work-item per (block column, view): prefix down the columns. sizes: (W, H) per view.
__kernel void block_cols(__global int* sat, __global const int* sat_off, __global const int2* sizes)
{
    int bx = get_global_id(0), v = get_global_id(1);
    int2 wh = sizes[v];
    int Wb = (wh.x + 7) >> 3, Hb = (wh.y + 7) >> 3;
    if (bx > Wb) return;
    __global int* t = sat + sat_off[v];
    int acc = 0;
    for (int by = 1; by <= Hb; by++) {
        acc += t[by * (Wb + 1) + bx];
        t[by * (Wb + 1) + bx] = acc;
    }
}

