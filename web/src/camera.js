// The camera model of sdk/camera.py: OpenCV pinhole, world -> camera p = R x + t, +z forward, +y down the image,
// pixel (x, y) centred at (x + 0.5, y + 0.5). Every number is a double here, as in Python; the splatter uploads
// float32 uniforms.

import {
  CAMERA_KEYS, DEFAULT_NEAR, FLOAT32_MAX, FOV_CLAMP_MARGIN, MAX_IMAGE_SIDE, MIN_FOCAL_PX, ROTATION_TOLERANCE,
} from './generated.js';
import { roundHalfEven } from './drive.js';

/** The size a (width, height) frame is drawn at under render settings `{render_scale, max_draw_pixels}`: its
 * render scale, or less where that would pass the pixel cap (`RenderSettings.draw_size` in sdk/render_settings.py,
 * whose `round` rounds halves to even). */
export function drawnSize(settings, width, height) {
  let scale = settings.render_scale;
  const cap = settings.max_draw_pixels ?? null;
  if (cap !== null && width * height * scale * scale > cap) scale = Math.sqrt(cap / (width * height));
  return [Math.max(1, roundHalfEven(width * scale)), Math.max(1, roundHalfEven(height * scale))];
}

export class CameraError extends Error {
  constructor(message) {
    super(message);
    this.name = 'CameraError';
  }
}

const finite = (v) => typeof v === 'number' && Number.isFinite(v);

const matvec = (M, v) => M.map((row) => row[0] * v[0] + row[1] * v[1] + row[2] * v[2]);
const transpose = (M) => [0, 1, 2].map((j) => M.map((row) => row[j]));
const matmul = (A, B) => A.map((row) => [0, 1, 2].map((j) => row[0] * B[0][j] + row[1] * B[1][j] + row[2] * B[2][j]));
const det = (M) => M[0][0] * (M[1][1] * M[2][2] - M[1][2] * M[2][1]) - M[0][1] * (M[1][0] * M[2][2] - M[1][2] * M[2][0])
  + M[0][2] * (M[1][0] * M[2][1] - M[1][1] * M[2][0]);

/** [3][3] rotation by `angle` radians about `axis` (normalised; Rodrigues, as sdk/camera.py `_axis_rotation`). */
function axisRotation(axis, angle) {
  const n = Math.hypot(...axis);
  const [x, y, z] = axis.map((v) => v / n);
  const k = [[0, -z, y], [z, 0, -x], [-y, x, 0]];
  const kk = matmul(k, k);
  const s = Math.sin(angle);
  const c = 1 - Math.cos(angle);
  return [0, 1, 2].map((i) => [0, 1, 2].map((j) => (i === j ? 1 : 0) + s * k[i][j] + c * kk[i][j]));
}

/** A rows x cols array of numbers (t: rows 3, cols 0 for a flat [3]), as sdk/camera.py `_matrix` takes it. */
function checkedMatrix(name, value, rows, cols) {
  const isRow = (row, n) => Array.isArray(row) && row.length === n && row.every((v) => typeof v === 'number');
  if (!(Array.isArray(value) && value.length === rows && value.every((row) => (cols ? isRow(row, cols)
    : typeof row === 'number')))) {
    throw new CameraError(`camera ${name} must be a ${cols ? `${rows}x${cols}` : rows} array of real numbers`);
  }
  return cols ? value.map((row) => row.slice()) : value.slice();
}

/** The checks of sdk/camera.py `Camera.validate`: every number usable in float32, R a proper rotation. */
function validate({ width, height, fx, fy, cx, cy, near, R, t }) {
  for (const [name, v] of [['width', width], ['height', height]]) {
    if (!(Number.isInteger(v) && v >= 1 && v <= MAX_IMAGE_SIDE)) {
      throw new CameraError(`camera ${name} must be an integer in 1..${MAX_IMAGE_SIDE}, got ${v}`);
    }
  }
  for (const [name, v] of [['fx', fx], ['fy', fy], ['cx', cx], ['cy', cy], ['near', near]]) {
    if (typeof v !== 'number') throw new CameraError(`camera ${name} must be a real number, got ${typeof v}`);
  }
  for (const [name, v] of [['fx', fx], ['fy', fy]]) {
    if (!(v >= MIN_FOCAL_PX && v <= FLOAT32_MAX)) {
      throw new CameraError(`camera focal length ${name} must be finite and > 0 (within float32), got ${v}`);
    }
  }
  for (const [name, v] of [['cx', cx], ['cy', cy]]) {
    if (!(Math.abs(v) <= FLOAT32_MAX)) throw new CameraError(`camera principal point ${name} must be finite, got ${v}`);
  }
  if (!(near > 0 && near <= FLOAT32_MAX)) throw new CameraError(`camera near plane must be finite and > 0, got ${near}`);
  if (![...R.flat(), ...t].every((v) => Math.abs(v) <= FLOAT32_MAX)) {
    throw new CameraError('camera extrinsics R and t must be finite (float32)');
  }
  // numpy's allclose(R R^T, I) with ROTATION_TOLERANCE as both its relative and absolute tolerance
  const product = matmul(R, transpose(R));
  const orthonormal = product.every((row, i) => row.every((v, j) => {
    const identity = i === j ? 1 : 0;
    return Math.abs(v - identity) <= ROTATION_TOLERANCE + ROTATION_TOLERANCE * identity;
  }));
  if (!orthonormal || det(R) < 0) throw new CameraError('camera R must be a proper rotation (orthonormal to 1e-5, det +1)');
}

export class Camera {
  /** `R` 3x3 rows, `t` [3]; checked as sdk/camera.py checks a camera (CameraError naming the first unusable field). */
  constructor({ width, height, fx, fy, cx, cy, R, t, near = DEFAULT_NEAR }) {
    const fields = { width, height, fx, fy, cx, cy, near, R: checkedMatrix('R', R, 3, 3), t: checkedMatrix('t', t, 3, 0) };
    validate(fields);
    Object.assign(this, fields);
  }

  /** A camera from its manifest description (`Camera.to_dict`): every key but "near" present, none converted. */
  static fromDict(data) {
    if (data === null || typeof data !== 'object' || Array.isArray(data)) {
      throw new CameraError('camera description must be an object');
    }
    const missing = CAMERA_KEYS.slice(0, -1).filter((key) => !Object.hasOwn(data, key));
    if (missing.length) throw new CameraError(`camera description is incomplete: missing ${missing.join(', ')}`);
    const fields = Object.fromEntries(CAMERA_KEYS.slice(0, -1).map((key) => [key, data[key]]));
    return new Camera({ ...fields, near: Object.hasOwn(data, 'near') ? data.near : DEFAULT_NEAR });
  }

  toDict() {
    return Object.fromEntries(CAMERA_KEYS.map((key) => [key, this[key]]));
  }

  /** The same view at another resolution: intrinsics scale with the image (`Camera.resized`). */
  resized(width, height) {
    const sx = width / this.width;
    const sy = height / this.height;
    return new Camera({ ...this.toDict(), width, height, fx: this.fx * sx, fy: this.fy * sy, cx: this.cx * sx,
      cy: this.cy * sy });
  }

  /** Camera centre in world coordinates, -R^T t. */
  center() {
    const { R, t } = this;
    return [0, 1, 2].map((j) => -(R[0][j] * t[0] + R[1][j] * t[1] + R[2][j] * t[2]));
  }

  /** This camera swung around `target` [3]: by yaw about its own up axis, then by pitch about its right axis, same
   * intrinsics and distance (`Camera.orbited`): a novel view of what it looks at. */
  orbited(yawDeg, pitchDeg, target) {
    if (![yawDeg, pitchDeg, ...target].every(finite) || target.length !== 3) {
      throw new CameraError('orbit yaw, pitch and target must be finite numbers (target: 3)');
    }
    let turn = axisRotation(this.R[1].map((v) => -v), yawDeg * Math.PI / 180);
    turn = matmul(axisRotation(matvec(turn, this.R[0]), pitchDeg * Math.PI / 180), turn);
    const c = this.center();
    const offset = matvec(turn, [0, 1, 2].map((k) => c[k] - target[k]));
    const eye = [0, 1, 2].map((k) => target[k] + offset[k]);
    const R = matmul(this.R, transpose(turn));
    return new Camera({ ...this.toDict(), R, t: matvec(R, eye).map((v) => -v) });
  }

  /** This camera moved along its view toward `target` [3] (factor < 1) or away (> 1): a zoom that keeps the
   * intrinsics. */
  dollied(factor, target) {
    if (!(finite(factor) && factor > 0) || target.length !== 3 || !target.every(finite)) {
      throw new CameraError('dolly factor must be a finite number > 0 and target 3 finite numbers');
    }
    const c = this.center();
    const eye = [0, 1, 2].map((k) => target[k] + factor * (c[k] - target[k]));
    return new Camera({ ...this.toDict(), t: matvec(this.R, eye).map((v) => -v) });
  }

  /** (x_min, x_max, y_min, y_max) of x/z and y/z before the projection Jacobian (docs/numerics.md). */
  fovClampLimits() {
    const mx = FOV_CLAMP_MARGIN * this.width / (2.0 * this.fx);
    const my = FOV_CLAMP_MARGIN * this.height / (2.0 * this.fy);
    return [-this.cx / this.fx - mx, (this.width - this.cx) / this.fx + mx, -this.cy / this.fy - my,
      (this.height - this.cy) / this.fy + my];
  }
}
