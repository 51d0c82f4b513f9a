// The composited frame in the page (runtime/composite.py; docs/compositing.md):
//
//     I = (1 - M) I_ori + M F(x),     x = C + (1 - M) I_ori
//
// C the head's premultiplied colour (renderFrame's 'rgba_float', no background), M the clip's mask, F the bundle's
// `inpaint` graph run on the crop around the mask's support (plus CROP_MARGIN_PX, sides rounded up to
// CROP_MULTIPLE, kept inside the frame; edge pixels repeated when the frame is smaller). Every pixel where M is 0
// is the reference frame's. The same float32 steps as the Python runtime's, in the same order (Math.fround).

import { CROP_MARGIN_PX, CROP_MULTIPLE } from './generated.js';

const f32 = Math.fround;

/** [start, length, pad] of the span holding [lo, hi) plus `margin`, length a multiple of `multiple`, inside
 * [0, size) where it fits (pad > 0 only when size itself is too short): composite.py `_span`. */
function span(lo, hi, size, margin, multiple) {
  const want = Math.min(hi + margin, size) - Math.max(lo - margin, 0);
  const length = Math.ceil(want / multiple) * multiple;
  if (length > size) return [0, size, length - size];
  const centre = Math.floor((lo + hi) / 2);
  const start = Math.min(Math.max(centre - Math.floor(length / 2), 0), size - length);
  return [start, length, 0];
}

/** The crop F needs for `mask` [h * w]: {top, left, height, width, padBottom, padRight}, or null for an empty
 * mask (the frame is the reference's). */
export function cropBox(mask, width, height, margin = CROP_MARGIN_PX, multiple = CROP_MULTIPLE) {
  let top = height;
  let bottom = -1;
  let left = width;
  let right = -1;
  for (let y = 0; y < height; y++) {
    for (let x = 0; x < width; x++) {
      if (mask[y * width + x] > 0) {
        if (y < top) top = y;
        bottom = y;
        if (x < left) left = x;
        if (x > right) right = x;
      }
    }
  }
  if (bottom < 0) return null;
  const [rowStart, rows, padBottom] = span(top, bottom + 1, height, margin, multiple);
  const [columnStart, columns, padRight] = span(left, right + 1, width, margin, multiple);
  return { top: rowStart, left: columnStart, height: rows, width: columns, padBottom, padRight };
}

/**
 * The composited frame, Uint8Array RGB [h * w * 3]: `head` Float32Array [h * w * 4] premultiplied (C, 1 - T),
 * `reference` Uint8Array RGB, `mask` Float32Array [h * w]; `inpaint({image, mask, coverage}, h, w)` runs F on the
 * crop's channel-first inputs and resolves to its output Float32Array [3 * h * w].
 */
export async function compositeFrame(head, reference, mask, width, height, inpaint) {
  const out = reference.slice();
  const box = cropBox(mask, width, height);
  if (box === null) return out;
  const h = box.height + box.padBottom;
  const w = box.width + box.padRight;
  const plane = h * w;
  const image = new Float32Array(3 * plane);
  const masks = new Float32Array(plane);
  const coverage = new Float32Array(plane);
  const original = new Float32Array(3 * plane); // (I_ori / 255) (1 - M), channel-last as composite.py keeps it
  const inv255 = f32(1 / 255);
  for (let y = 0; y < h; y++) {
    const row = Math.min(box.top + y, height - 1);
    for (let x = 0; x < w; x++) {
      const column = Math.min(box.left + x, width - 1);
      const source = row * width + column;
      const target = y * w + x;
      const m = mask[source];
      masks[target] = m;
      coverage[target] = head[4 * source + 3];
      const keep = f32(1 - m);
      for (let c = 0; c < 3; c++) {
        const o = f32(f32(reference[3 * source + c] * inv255) * keep);
        original[3 * target + c] = o;
        image[c * plane + target] = f32(head[4 * source + c] + o);
      }
    }
  }
  const filled = await inpaint({ image, mask: masks, coverage }, h, w);
  if (!(filled instanceof Float32Array) || filled.length !== 3 * plane) {
    throw new Error(`the inpainting graph returned ${filled?.length} values for a crop that needs ${3 * plane}`);
  }
  for (let y = 0; y < box.height; y++) {
    for (let x = 0; x < box.width; x++) {
      const target = y * w + x;
      const m = masks[target];
      if (!(m > 0)) continue;
      const pixel = 3 * ((box.top + y) * width + box.left + x);
      for (let c = 0; c < 3; c++) {
        let v = f32(f32(filled[c * plane + target] * m) + original[3 * target + c]);
        v = v < 0 ? 0 : v > 1 ? 1 : v;
        out[pixel + c] = Math.trunc(f32(f32(v * 255) + 0.5));
      }
    }
  }
  return out;
}
