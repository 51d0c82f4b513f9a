// The camera model of sdk/camera.py: OpenCV pinhole, world -> camera p = R x + t, +z forward, +y down the image,
// pixel (x, y) centred at (x + 0.5, y + 0.5). Every number is a double here, as in Python; the splatter uploads
// float32 uniforms.

import { DEFAULT_NEAR, FOV_CLAMP_MARGIN } from './generated.js';

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

export class Camera {
  /** `R` 3x3 rows, `t` [3]. */
  constructor({ width, height, fx, fy, cx, cy, R, t, near = DEFAULT_NEAR }) {
    if (!(Number.isInteger(width) && Number.isInteger(height) && width >= 1 && height >= 1 && width <= 16384
          && height <= 16384)) {
      throw new CameraError(`camera width and height must be integers in 1..16384, got ${width}x${height}`);
    }
    if (![fx, fy, cx, cy, near].every(finite) || !(fx > 0 && fy > 0 && near > 0)) {
      throw new CameraError('camera fx, fy (> 0), cx, cy and near (> 0) must be finite numbers');
    }
    if (!(Array.isArray(R) && R.length === 3 && R.every((row) => Array.isArray(row) && row.length === 3
          && row.every(finite)) && Array.isArray(t) && t.length === 3 && t.every(finite))) {
      throw new CameraError('camera R must be 3x3 and t 3 finite numbers');
    }
    Object.assign(this, { width, height, fx, fy, cx, cy, near });
    this.R = R.map((row) => row.slice());
    this.t = t.slice();
  }

  /** A camera from its manifest description (`Camera.to_dict`). */
  static fromDict(data) {
    if (data === null || typeof data !== 'object') throw new CameraError('camera description is not an object');
    return new Camera({ ...data, near: data.near ?? DEFAULT_NEAR });
  }

  toDict() {
    const { width, height, fx, fy, cx, cy, R, t, near } = this;
    return { width, height, fx, fy, cx, cy, R, t, near };
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
