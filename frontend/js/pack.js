// Packing splats into the renderer's RGBA32UI texture: 3 texels (12 uint32) a splat,
// 1024 splats a row.
//   texel 0: position x, y, z (float bits), RGBA (4 x u8)
//   texel 1: covariance xx, xy, xz, yy (float bits)
//   texel 2: covariance yz, zz (float bits), flags, index
// flags: bit 0 dynamic, bit 1 selected.

export const SPLATS_PER_ROW = 1024;
export const WORDS_PER_SPLAT = 12;
export const TEX_WIDTH = 3 * SPLATS_PER_ROW;
export const FLAG_DYNAMIC = 1, FLAG_SELECTED = 2;

export function textureRows(count) {
  return Math.max(1, Math.ceil(count / SPLATS_PER_ROW));
}

// Writes `set` (a parsed buffer) at splat offset `offset` of `words` (Uint32Array).
export function packSet(words, offset, set, flags, selected = null) {
  const f32 = new Float32Array(words.buffer, words.byteOffset, words.length);
  const u8 = new Uint8Array(words.buffer, words.byteOffset, words.byteLength);
  for (let i = 0; i < set.count; i++) {
    const w = (offset + i) * WORDS_PER_SPLAT;
    f32[w] = set.positions[3 * i]; f32[w + 1] = set.positions[3 * i + 1]; f32[w + 2] = set.positions[3 * i + 2];
    u8.set(set.rgba.subarray(4 * i, 4 * i + 4), 4 * (w + 3));
    for (let k = 0; k < 4; k++) f32[w + 4 + k] = set.covariances[6 * i + k];
    f32[w + 8] = set.covariances[6 * i + 4]; f32[w + 9] = set.covariances[6 * i + 5];
    words[w + 10] = flags | (selected && selected.has(set.index[i]) ? FLAG_SELECTED : 0);
    words[w + 11] = set.index[i];
  }
}

export function unpackSplat(words, i) {
  const f32 = new Float32Array(words.buffer, words.byteOffset, words.length);
  const u8 = new Uint8Array(words.buffer, words.byteOffset, words.byteLength);
  const w = i * WORDS_PER_SPLAT;
  return {
    position: [f32[w], f32[w + 1], f32[w + 2]],
    rgba: Array.from(u8.subarray(4 * (w + 3), 4 * (w + 3) + 4)),
    covariance: [f32[w + 4], f32[w + 5], f32[w + 6], f32[w + 7], f32[w + 8], f32[w + 9]],
    flags: words[w + 10], index: words[w + 11],
  };
}
