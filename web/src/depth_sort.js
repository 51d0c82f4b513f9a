// A frame's Gaussians packed, culled, depth-sorted front to back and split into draw runs: what the Python
// runtime's `GLSplatter.prepare` does (runtime/splat/common.py `pack_gaussians`; runtime/splat/gl.py `plan_runs`;
// runtime/splat/depth_sort.py `view_depth`, `depth_order`; docs/porting.md 3.2-3.4). Pure functions: the sort
// worker (sort_worker.js) runs them off the main thread, and Node can import them.

import {
  EXTENT_SIGMAS, FLOATS_PER_SPLAT, KEY_LEVELS_16, LOW_PASS_PX2, POINT_BOUND_SAFETY, QUAD_SLACK_PX, RUN_COST_IN_SPLATS,
} from './generated.js';

export { FLOATS_PER_SPLAT };
const f32 = Math.fround;

/** Deform outputs (means [N*3], cov3d [N*6], rgb [N*3], opacity [N]) -> rows [N*13] (`pack_gaussians`). */
export function packGaussians(means, cov3d, rgb, opacity) {
  const n = opacity.length;
  if (means.length !== 3 * n || cov3d.length !== 6 * n || rgb.length !== 3 * n) {
    throw new Error(`deform outputs disagree: means ${means.length / 3}, cov3d ${cov3d.length / 6}, rgb `
      + `${rgb.length / 3}, opacity ${n} Gaussians`);
  }
  const rows = new Float32Array(n * FLOATS_PER_SPLAT);
  for (let i = 0, o = 0; i < n; i++, o += FLOATS_PER_SPLAT) {
    for (let k = 0; k < 3; k++) rows[o + k] = means[3 * i + k];
    for (let k = 0; k < 6; k++) rows[o + 3 + k] = cov3d[6 * i + k];
    for (let k = 0; k < 3; k++) rows[o + 9 + k] = rgb[3 * i + k];
    rows[o + 12] = opacity[i];
  }
  return rows;
}

/** Indices of the rows to draw (finite, z >= near) and their float32 view depth, summed as numpy does. */
export function visible(rows, camera) {
  const n = rows.length / FLOATS_PER_SPLAT;
  const r = camera.R[2].map(f32);
  const t = f32(camera.t[2]);
  const near = f32(camera.near);
  const kept = new Uint32Array(n);
  let count = 0;
  const depth = new Float32Array(n);
  for (let i = 0; i < n; i++) {
    const o = i * FLOATS_PER_SPLAT;
    const z = f32(f32(f32(f32(rows[o] * r[0]) + f32(rows[o + 1] * r[1])) + f32(rows[o + 2] * r[2])) + t);
    depth[i] = z;
    let finite = Number.isFinite(z) && z >= near;
    for (let k = 0; finite && k < FLOATS_PER_SPLAT; k++) finite = Number.isFinite(rows[o + k]);
    if (finite) kept[count++] = i;
  }
  return { kept: kept.subarray(0, count), depth };
}

/** Stable LSD radix sort of `items` by 32-bit unsigned `keys` (8 bits a pass): equal keys keep their order.
 * By hand: a few lines, and no library sorts a key array with a payload without a comparator per element. */
function radixSort(keys, items, passes) {
  let k = keys;
  let v = items;
  let k2 = new Uint32Array(k.length);
  let v2 = new Uint32Array(v.length);
  const counts = new Uint32Array(256);
  for (let pass = 0; pass < passes; pass++) {
    const shift = 8 * pass;
    counts.fill(0);
    for (let i = 0; i < k.length; i++) counts[(k[i] >>> shift) & 255]++;
    let sum = 0;
    for (let b = 0; b < 256; b++) {
      const c = counts[b];
      counts[b] = sum;
      sum += c;
    }
    for (let i = 0; i < k.length; i++) {
      const slot = counts[(k[i] >>> shift) & 255]++;
      k2[slot] = k[i];
      v2[slot] = v[i];
    }
    [k, k2] = [k2, k];
    [v, v2] = [v2, v];
  }
  return v;
}

/** Front-to-back order of the kept rows: stable sort on float32 depth (the bits of a positive float32 order like
 * its value), or on 16-bit keys over the frame's depth range (`stable_argsort_16bit`). */
export function depthOrder(rows, camera, keyBits = 32) {
  const { kept, depth } = visible(rows, camera);
  const keys = new Uint32Array(kept.length);
  if (keyBits === 32) {
    const bits = new Uint32Array(depth.buffer);
    for (let i = 0; i < kept.length; i++) keys[i] = bits[kept[i]];
    return radixSort(keys, kept, 4);
  }
  let lo = Infinity;
  let hi = -Infinity;
  for (const i of kept) {
    lo = Math.min(lo, depth[i]);
    hi = Math.max(hi, depth[i]);
  }
  const scale = hi > lo ? KEY_LEVELS_16 / (hi - lo) : 0.0;
  for (let i = 0; i < kept.length; i++) keys[i] = Math.trunc(Math.min((depth[kept[i]] - lo) * scale, KEY_LEVELS_16));
  return radixSort(keys, kept, 2);
}

/** An upper bound of each sorted row's extent radius in px, in double precision (`extent_radius_bound`). */
function extentRadiusBound(rows, i, camera, limits) {
  const o = i * FLOATS_PER_SPLAT;
  const { R, t } = camera;
  const x = rows[o];
  const y = rows[o + 1];
  const z = rows[o + 2];
  const p0 = x * R[0][0] + y * R[0][1] + z * R[0][2] + t[0];
  const p1 = x * R[1][0] + y * R[1][1] + z * R[1][2] + t[1];
  const p2 = x * R[2][0] + y * R[2][1] + z * R[2][2] + t[2];
  const xz = Math.min(Math.max(p0 / p2, limits[0]), limits[1]);
  const yz = Math.min(Math.max(p1 / p2, limits[2]), limits[3]);
  const jacobian = (camera.fx ** 2 * (1 + xz * xz) + camera.fy ** 2 * (1 + yz * yz)) / (p2 * p2);
  const frobenius = Math.sqrt(rows[o + 3] ** 2 + 2 * rows[o + 4] ** 2 + 2 * rows[o + 5] ** 2 + rows[o + 6] ** 2
    + 2 * rows[o + 7] ** 2 + rows[o + 8] ** 2);
  const bound = EXTENT_SIGMAS * Math.sqrt(jacobian * frobenius + LOW_PASS_PX2);
  return Number.isFinite(bound) ? bound : Infinity;
}

/** Draw runs [start, stop, asQuads] of the sorted rows: points where a point sprite surely holds the box
 * (`GLSplatter.plan_runs`); all quads when the runs would cost more than points save. */
export function planRuns(rows, camera, limits, maxPointSize) {
  const n = rows.length / FLOATS_PER_SPLAT;
  if (n === 0) return [];
  if (!(maxPointSize > 0)) return [[0, n, true]];
  const runs = [];
  let points = 0;
  for (let i = 0; i < n; i++) {
    const side = 2.0 * POINT_BOUND_SAFETY * extentRadiusBound(rows, i, camera, limits) + 2.0 + 2.0 * QUAD_SLACK_PX;
    const quad = side > maxPointSize;
    if (!quad) points++;
    if (runs.length && runs[runs.length - 1][2] === quad) runs[runs.length - 1][1] = i + 1;
    else runs.push([i, i + 1, quad]);
  }
  return runs.length * RUN_COST_IN_SPLATS < points ? runs : [[0, n, true]];
}

/** `depthOrder` with a sort interval (runtime/splat/depth_sort.py `DepthSorter`): a full sort every `interval` frames,
 * the last order reused in between, still culled afresh; a newly visible row, another Gaussian count or another
 * view sorts anew. Calls must come in frame order. */
export class DepthSorter {
  constructor(interval = 1, keyBits = 32) {
    this.interval = interval;
    this.keyBits = keyBits;
    this.order = null;
    this.view = null;
    this.age = 0;
  }

  sort(rows, camera) {
    if (this.interval === 1) return depthOrder(rows, camera, this.keyBits);
    const view = JSON.stringify([rows.length, camera.R, camera.t, camera.width, camera.height, camera.near]);
    if (this.order !== null && this.age < this.interval - 1 && view === this.view) {
      const { kept } = visible(rows, camera);
      const keep = new Uint8Array(rows.length / FLOATS_PER_SPLAT);
      for (const i of kept) keep[i] = 1;
      const reused = this.order.filter((i) => keep[i]);
      if (reused.length === kept.length) { // no newly visible row: the reused order is complete
        this.age += 1;
        return reused;
      }
    }
    this.order = depthOrder(rows, camera, this.keyBits);
    this.view = view;
    this.age = 0;
    return this.order;
  }
}

/** The whole preparation of one frame: packed rows in draw order and their runs. `camera` is a plain object
 * (R, t, fx, fy, width, height, near), `limits` its fov clamp limits, `sorter` a DepthSorter. */
export function prepareFrame({ means, cov3d, rgb, opacity }, camera, limits, maxPointSize, sorter) {
  const packed = packGaussians(means, cov3d, rgb, opacity);
  const order = sorter.sort(packed, camera);
  const rows = new Float32Array(order.length * FLOATS_PER_SPLAT);
  for (let j = 0; j < order.length; j++) {
    const from = order[j] * FLOATS_PER_SPLAT;
    const to = j * FLOATS_PER_SPLAT;
    for (let k = 0; k < FLOATS_PER_SPLAT; k++) rows[to + k] = packed[from + k];
  }
  return { rows, runs: planRuns(rows, camera, limits, maxPointSize) };
}
