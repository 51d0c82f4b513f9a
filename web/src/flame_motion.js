// FLAME motion: per-frame FLAME parameters as a tracker writes them (GaussianAvatars' flame_param.npz), the
// browser's twin of sdk/flame_motion.py (docs/import.md, "Motion files"; docs/web.md, "Motion files").
//
// A motion is {table: Float32Array [frames * (nExpr + 18)], frames, nExpr, fps}: per row the expression, then
// flame_pose (rotation, neck, jaw, left eye, right eye: axis-angle) and the head translation, the layout of a
// bundle's `motion_track` buffer.

import { DriveError, resampleAtFps } from './drive.js';
import { FLAME_MOTION_KEYS, MAX_DRIVE_MAGNITUDE, TABLE_POSE_COLUMNS } from './generated.js';
import { readNpz } from './npz.js';

const POSE_DIM = TABLE_POSE_COLUMNS - 3;

/** `value` ({shape, kind, values} from readNpz, or nested arrays of numbers) as a checked float64 [rows, width]
 * table (`count` rows when non-zero; `width` null: any >= 1): sdk/flame_motion.py `_table`. */
function table(name, value, count, width, where) {
  let shape;
  let values;
  if (value && value.values !== undefined && Array.isArray(value.shape)) {
    if (value.values === null) throw new DriveError(`${where}: '${name}' holds ${value.kind === 'U' ? 'unicode' : 'byte'} strings, not numbers`);
    ({ shape, values } = value);
  } else if (Array.isArray(value) && value.every((row) => Array.isArray(row) || ArrayBuffer.isView(row))) {
    const widths = new Set(value.map((row) => row.length));
    if (widths.size > 1) throw new DriveError(`${where}: '${name}' has rows of different lengths`);
    shape = [value.length, value.length ? value[0].length : 0];
    values = Float64Array.from(value.flatMap((row) => Array.from(row, (v) => (typeof v === 'number' ? v : NaN))));
  } else {
    throw new DriveError(`${where}: '${name}' must be a table of numbers (rows of equal length)`);
  }
  const expected = `[${count || 'T >= 1'}, ${width ?? 'E'}]`;
  if (shape.length !== 2 || shape[0] < 1 || (count && shape[0] !== count) || (width !== null && shape[1] !== width)
      || shape[1] < 1) {
    throw new DriveError(`${where}: '${name}' has shape [${shape.join(', ')}], expected ${expected}`);
  }
  for (let i = 0; i < values.length; i++) {
    if (!(Math.abs(values[i]) <= MAX_DRIVE_MAGNITUDE)) {
      const [row, column] = [Math.floor(i / shape[1]), i % shape[1]];
      throw new DriveError(`${where}: ${name}[${row}, ${column}] = ${values[i]} is not finite within ${MAX_DRIVE_MAGNITUDE}`);
    }
  }
  return { rows: shape[0], width: shape[1], values };
}

/** A FLAME motion from GaussianAvatars' per-frame keys (`expr`, `rotation`, `neck_pose`, `jaw_pose`, `eyes_pose`,
 * `translation`), at `fps`; DriveError naming a missing or mis-shaped key (sdk/flame_motion.py
 * `parse_flame_motion`). */
export function parseFlameMotion(arrays, fps, where = 'motion') {
  const missing = FLAME_MOTION_KEYS.map(([key]) => key).filter((key) => !(key in arrays));
  if (missing.length) {
    throw new DriveError(`${where}: a FLAME motion needs ${FLAME_MOTION_KEYS.map(([k]) => k).join(', ')}; missing `
      + `${missing.join(', ')}`);
  }
  const expr = table('expr', arrays.expr, 0, null, where);
  const parts = Object.fromEntries(FLAME_MOTION_KEYS.slice(1).map(([key, width]) => [key,
    table(key, arrays[key], expr.rows, width, where)]));
  if (!(Number.isFinite(fps) && fps > 0)) throw new DriveError(`motion fps must be positive, got ${fps}`);
  const width = expr.width + TABLE_POSE_COLUMNS;
  const out = new Float32Array(expr.rows * width);
  const columns = [[expr, 0], [parts.rotation, expr.width], [parts.neck_pose, expr.width + 3],
    [parts.jaw_pose, expr.width + 6], [parts.eyes_pose, expr.width + 9], [parts.translation, expr.width + POSE_DIM]];
  for (let r = 0; r < expr.rows; r++) {
    for (const [part, at] of columns) {
      for (let k = 0; k < part.width; k++) out[r * width + at + k] = part.values[r * part.width + k];
    }
  }
  return { table: out, frames: expr.rows, nExpr: expr.width, fps };
}

/** A FLAME motion npz's bytes -> motion at `fps` (the file records no rate), reading only the motion's keys,
 * never unpickling (sdk/flame_motion.py `load_flame_motion`). */
export function readFlameMotion(bytes, fps, where = 'motion file') {
  const arrays = readNpz(bytes, { keys: FLAME_MOTION_KEYS.map(([key]) => key), where,
    what: 'an npz of per-frame FLAME parameters', makeError: (message) => new DriveError(message) });
  return parseFlameMotion(arrays, fps, where);
}

/** A bundle's motion table (float32 [rows * width], width = nExpr + 18) as a motion at `fps`. */
export function flameMotionFromTable(data, rows, width, fps) {
  if (!(width > TABLE_POSE_COLUMNS && rows >= 1 && data.length === rows * width)) {
    throw new DriveError(`a FLAME motion table is [T, E + ${TABLE_POSE_COLUMNS}], got [${rows}, ${width}]`);
  }
  return { table: Float32Array.from(data), frames: rows, nExpr: width - TABLE_POSE_COLUMNS, fps };
}

/** The motion for a speaker of `nExpr` coefficients: zero-padded when it has fewer; a DriveError when it moves a
 * coefficient the speaker does not have (`FlameMotion.with_expressions`). */
export function withExpressions(motion, nExpr) {
  if (nExpr === motion.nExpr) return motion;
  const from = motion.nExpr + TABLE_POSE_COLUMNS;
  const to = nExpr + TABLE_POSE_COLUMNS;
  if (nExpr < motion.nExpr) {
    for (let r = 0; r < motion.frames; r++) {
      for (let k = nExpr; k < motion.nExpr; k++) {
        if (motion.table[r * from + k] !== 0) {
          throw new DriveError(`the motion has ${motion.nExpr} expression coefficients and moves coefficient ${k}; `
            + `this speaker has ${nExpr}`);
        }
      }
    }
  }
  const out = new Float32Array(motion.frames * to);
  const kept = Math.min(nExpr, motion.nExpr);
  for (let r = 0; r < motion.frames; r++) {
    out.set(motion.table.subarray(r * from, r * from + kept), r * to);
    out.set(motion.table.subarray(r * from + motion.nExpr, (r + 1) * from), r * to + nExpr);
  }
  return { ...motion, table: out, nExpr };
}

/** The motion resampled linearly in time (every column) to `fps` over the same duration (`FlameMotion.at_fps`). */
export function flameMotionAtFps(motion, fps) {
  if (Math.abs(fps - motion.fps) < 1e-9) return motion;
  const width = motion.nExpr + TABLE_POSE_COLUMNS;
  const { rows, frames } = resampleAtFps(motion.table, motion.frames, width, motion.fps, fps);
  return { table: Float32Array.from(rows), frames, nExpr: motion.nExpr, fps };
}
