// WebGL2 splatter: the Python runtime's GL renderer (runtime/splat/gl.py `GLSplatter`, docs/porting.md 3.4-3.5)
// with the same GLSL ES 3.00 programs (generated.js, from shaders/), the same draw state and read-back.
//
// Framebuffer precision: the contract accumulates in float. RGBA32F needs EXT_color_buffer_float (render to it)
// and EXT_float_blend (blend into it); without both the splatter falls back to RGBA16F (EXT_color_buffer_float or
// EXT_color_buffer_half_float) and then to RGBA8, and says so in `precision` and `fallback`
// (docs/precision.md measures those tiers: 53.0 and 44.3 dB head PSNR on the demo speaker). The render-scale pass
// samples RGBA32F bilinearly only with OES_texture_float_linear (else nearest, and `fallback` says so).

import { halfToFloat } from './codecs.js';
import { FLOATS_PER_SPLAT } from './depth_sort.js';
import { PROGRAMS } from './generated.js';

const STRIDE = FLOATS_PER_SPLAT * 4;
const ATTRIBUTES = [['in_mean', 3, 0], ['in_cov_a', 3, 12], ['in_cov_b', 3, 24], ['in_rgba', 4, 36]];
const FORMATS = { float32: 'RGBA32F', float16: 'RGBA16F', uint8: 'RGBA8' };

export class RenderError extends Error {
  constructor(message) {
    super(message);
    this.name = 'RenderError';
  }
}

function compile(gl, name, type, source) {
  const shader = gl.createShader(type);
  gl.shaderSource(shader, source);
  gl.compileShader(shader);
  if (!gl.getShaderParameter(shader, gl.COMPILE_STATUS)) {
    throw new RenderError(`shader of program '${name}' failed to compile: ${gl.getShaderInfoLog(shader)}`);
  }
  return shader;
}

function program(gl, name) {
  const { vertex, fragment } = PROGRAMS[name];
  const p = gl.createProgram();
  gl.attachShader(p, compile(gl, name, gl.VERTEX_SHADER, vertex));
  gl.attachShader(p, compile(gl, name, gl.FRAGMENT_SHADER, fragment));
  gl.linkProgram(p);
  if (!gl.getProgramParameter(p, gl.LINK_STATUS)) {
    throw new RenderError(`program '${name}' failed to link: ${gl.getProgramInfoLog(p)}`);
  }
  const uniforms = {};
  for (let i = 0; i < gl.getProgramParameter(p, gl.ACTIVE_UNIFORMS); i++) {
    const info = gl.getActiveUniform(p, i);
    uniforms[info.name] = gl.getUniformLocation(p, info.name);
  }
  const attributes = Object.fromEntries(ATTRIBUTES.map(([a]) => [a, gl.getAttribLocation(p, a)]));
  return { program: p, uniforms, attributes };
}

export class WebGLSplatter {
  /**
   * `canvas`: an HTMLCanvasElement or OffscreenCanvas to take a WebGL2 context from (default a 1x1
   * OffscreenCanvas: frames are drawn offscreen and read back). `renderTarget`: 'float32' (the contract's),
   * 'float16' or 'uint8'; a target the browser cannot blend into falls back as described above. `pointSprites`:
   * false draws every Gaussian as an instanced quad (the same pixels; which is faster depends on the rasteriser).
   */
  constructor({ canvas = null, renderTarget = 'float32', pointSprites = true } = {}) {
    this.canvas = canvas ?? new OffscreenCanvas(1, 1);
    const gl = this.canvas.getContext('webgl2', { antialias: false, depth: false, stencil: false, alpha: true,
      premultipliedAlpha: false, preserveDrawingBuffer: true });
    if (!gl) throw new RenderError('this browser gives no WebGL2 context');
    this.gl = gl;
    this.extensions = Object.fromEntries(['EXT_color_buffer_float', 'EXT_float_blend', 'OES_texture_float_linear',
      'EXT_color_buffer_half_float'].map((name) => [name, Boolean(gl.getExtension(name))]));
    this.precision = this._precision(renderTarget);
    this.fallback = this.precision === renderTarget ? null
      : `render target ${renderTarget} is not available here (extensions: ${JSON.stringify(this.extensions)}); `
        + `drawing into ${FORMATS[this.precision]}`;
    // 0: every Gaussian as an instanced quad (the same pixels), as GLSplatter(point_sprites=False).
    this.maxPointSize = pointSprites ? gl.getParameter(gl.ALIASED_POINT_SIZE_RANGE)[1] : 0;
    this.programs = Object.fromEntries(Object.keys(PROGRAMS).map((name) => [name, program(gl, name)]));
    this.buffer = gl.createBuffer();
    this.capacity = 0;
    this.pointVao = this._vao(this.programs.points, 0);
    this.quadVao = this._vao(this.programs.quads, 1);
    this.emptyVao = gl.createVertexArray();
    this.targets = new Map();
    this.renderer = gl.getParameter(gl.RENDERER);
  }

  _precision(wanted) {
    const ext = this.extensions;
    const float32 = ext.EXT_color_buffer_float && ext.EXT_float_blend;
    const float16 = ext.EXT_color_buffer_float || ext.EXT_color_buffer_half_float;
    if (wanted === 'float32' && float32) return 'float32';
    if ((wanted === 'float32' || wanted === 'float16') && float16) return 'float16';
    return 'uint8';
  }

  _vao(prog, divisor) {
    const gl = this.gl;
    const vao = gl.createVertexArray();
    gl.bindVertexArray(vao);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.buffer);
    for (const [name, size, offset] of ATTRIBUTES) {
      const location = prog.attributes[name];
      gl.enableVertexAttribArray(location);
      gl.vertexAttribPointer(location, size, gl.FLOAT, false, STRIDE, offset);
      gl.vertexAttribDivisor(location, divisor);
    }
    gl.bindVertexArray(null);
    return vao;
  }

  /** A framebuffer of one size (cached): RGBA32F / RGBA16F / RGBA8 texture, no depth. */
  _target(width, height) {
    const key = `${width}x${height}`;
    if (this.targets.has(key)) return this.targets.get(key);
    const gl = this.gl;
    const texture = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, texture);
    gl.texStorage2D(gl.TEXTURE_2D, 1, gl[FORMATS[this.precision]], width, height);
    const linear = this.precision !== 'float32' || this.extensions.OES_texture_float_linear;
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, linear ? gl.LINEAR : gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, linear ? gl.LINEAR : gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
    const fbo = gl.createFramebuffer();
    gl.bindFramebuffer(gl.FRAMEBUFFER, fbo);
    gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, texture, 0);
    const status = gl.checkFramebufferStatus(gl.FRAMEBUFFER);
    if (status !== gl.FRAMEBUFFER_COMPLETE) {
      throw new RenderError(`a ${FORMATS[this.precision]} framebuffer of ${key} is not complete (status ${status})`);
    }
    const target = { texture, fbo, width, height, linear };
    this.targets.set(key, target);
    if (this.targets.size > 4) { // the four most recent sizes, as the Python runtime keeps
      const [oldKey, old] = this.targets.entries().next().value;
      gl.deleteFramebuffer(old.fbo);
      gl.deleteTexture(old.texture);
      this.targets.delete(oldKey);
    }
    return target;
  }

  _setCamera(camera) {
    const gl = this.gl;
    const { R, t } = camera;
    const columnMajor = new Float32Array([R[0][0], R[1][0], R[2][0], R[0][1], R[1][1], R[2][1], R[0][2], R[1][2],
      R[2][2]]);
    const limits = camera.fovClampLimits();
    for (const name of ['points', 'quads']) {
      const { program: p, uniforms: u } = this.programs[name];
      gl.useProgram(p);
      gl.uniformMatrix3fv(u.u_R, false, columnMajor);
      gl.uniform3f(u.u_t, t[0], t[1], t[2]);
      gl.uniform4f(u.u_intrinsics, camera.fx, camera.fy, camera.cx, camera.cy);
      gl.uniform2f(u.u_image_size, camera.width, camera.height);
      gl.uniform4f(u.u_fov_limits, ...limits);
    }
  }

  /**
   * Upload, splat and read back one prepared frame ({rows, runs} in draw order, depth_sort.js) seen by `camera`
   * (at the draw size) -> {pixels, width, height, timings}. `outputSize` [W, H]: upscale to it (render scale < 1).
   * `output`: 'uint8' (RGB, top row first), 'float' (RGB float32: C + T * background) or 'rgba_float'
   * (premultiplied (C, 1 - T), no background pass).
   */
  async draw({ rows, runs }, camera, background, { output = 'uint8', outputSize = null } = {}) {
    const gl = this.gl;
    const timings = {};
    let start = performance.now();
    gl.bindBuffer(gl.ARRAY_BUFFER, this.buffer);
    if (rows.byteLength > this.capacity) {
      this.capacity = Math.max(rows.byteLength, 2 * this.capacity);
      gl.bufferData(gl.ARRAY_BUFFER, this.capacity, gl.DYNAMIC_DRAW);
    }
    if (rows.byteLength) gl.bufferSubData(gl.ARRAY_BUFFER, 0, rows);
    this._setCamera(camera);
    let target = this._target(camera.width, camera.height);
    timings.upload = (performance.now() - start) / 1000;

    start = performance.now();
    gl.bindFramebuffer(gl.FRAMEBUFFER, target.fbo);
    gl.viewport(0, 0, target.width, target.height);
    gl.disable(gl.DEPTH_TEST);
    gl.disable(gl.CULL_FACE);
    gl.disable(gl.SCISSOR_TEST);
    gl.clearColor(0, 0, 0, 0);
    gl.clear(gl.COLOR_BUFFER_BIT);
    gl.enable(gl.BLEND);
    gl.blendEquation(gl.FUNC_ADD);
    gl.blendFunc(gl.ONE_MINUS_DST_ALPHA, gl.ONE); // "under": dst += (1 - dst.a) * src
    for (const [a, b, asQuads] of runs) {
      if (asQuads) {
        const { program: p, attributes } = this.programs.quads;
        gl.useProgram(p);
        gl.bindVertexArray(this.quadVao);
        for (const [name, size, offset] of ATTRIBUTES) { // WebGL2 has no base instance: move the pointers to row a
          gl.vertexAttribPointer(attributes[name], size, gl.FLOAT, false, STRIDE, offset + STRIDE * a);
        }
        gl.drawArraysInstanced(gl.TRIANGLE_STRIP, 0, 4, b - a);
      } else {
        gl.useProgram(this.programs.points.program);
        gl.bindVertexArray(this.pointVao);
        gl.drawArrays(gl.POINTS, a, b - a);
      }
    }
    gl.bindVertexArray(this.emptyVao);
    if (output !== 'rgba_float') {
      const { program: p, uniforms } = this.programs.background;
      gl.useProgram(p);
      gl.uniform3f(uniforms.u_background, background[0], background[1], background[2]);
      gl.drawArrays(gl.TRIANGLES, 0, 3);
    }
    if (outputSize && (outputSize[0] !== target.width || outputSize[1] !== target.height)) {
      const source = target;
      target = this._target(outputSize[0], outputSize[1]);
      gl.bindFramebuffer(gl.FRAMEBUFFER, target.fbo);
      gl.viewport(0, 0, target.width, target.height);
      gl.disable(gl.BLEND);
      const { program: p, uniforms } = this.programs.upscale;
      gl.useProgram(p);
      gl.activeTexture(gl.TEXTURE0);
      gl.bindTexture(gl.TEXTURE_2D, source.texture);
      gl.uniform1i(uniforms.u_source, 0);
      gl.uniform2f(uniforms.u_output_size, target.width, target.height);
      gl.drawArrays(gl.TRIANGLES, 0, 3);
      gl.enable(gl.BLEND);
    }
    gl.bindVertexArray(null);
    await this._drawn(); // so that "draw" and "readback" are timed apart
    timings.draw = (performance.now() - start) / 1000;

    start = performance.now();
    const { width, height } = target;
    let pixels;
    if (this.precision === 'uint8') {
      const rgba = new Uint8Array(width * height * 4);
      gl.readPixels(0, 0, width, height, gl.RGBA, gl.UNSIGNED_BYTE, rgba); // GL rounds to nearest, as to_uint8
      pixels = output === 'uint8' ? dropAlpha(rgba, Uint8Array)
        : Float32Array.from(output === 'rgba_float' ? rgba : dropAlpha(rgba, Uint8Array), (v) => v / 255);
    } else {
      const rgba = new Float32Array(width * height * 4); // ES guarantees RGBA read-backs only: drop alpha after
      if (this.extensions.EXT_color_buffer_float) {
        gl.readPixels(0, 0, width, height, gl.RGBA, gl.FLOAT, rgba);
      } else { // RGBA16F through EXT_color_buffer_half_float alone: read half floats
        const halves = new Uint16Array(width * height * 4);
        gl.readPixels(0, 0, width, height, gl.RGBA, gl.HALF_FLOAT, halves);
        for (let i = 0; i < halves.length; i++) rgba[i] = halfToFloat(halves[i]);
      }
      if (output === 'rgba_float') pixels = rgba;
      else if (output === 'float') pixels = dropAlpha(rgba, Float32Array);
      else pixels = rgbUint8(rgba);
    }
    timings.readback = (performance.now() - start) / 1000;
    return { pixels, width, height, timings };
  }

  /** Resolves when the GPU has run every command issued so far: a fence polled between tasks (WebGL2 allows no
   * blocking wait, and Chromium's gl.finish() returns before its GPU process has drawn). */
  async _drawn() {
    const gl = this.gl;
    const sync = gl.fenceSync(gl.SYNC_GPU_COMMANDS_COMPLETE, 0);
    gl.flush();
    try {
      while (gl.clientWaitSync(sync, 0, 0) === gl.TIMEOUT_EXPIRED) {
        await new Promise((resolve) => { setTimeout(resolve, 0); });
      }
    } finally {
      gl.deleteSync(sync);
    }
  }

  release() {
    const gl = this.gl;
    for (const target of this.targets.values()) {
      gl.deleteFramebuffer(target.fbo);
      gl.deleteTexture(target.texture);
    }
    this.targets.clear();
    for (const { program: p } of Object.values(this.programs)) gl.deleteProgram(p);
    gl.deleteBuffer(this.buffer);
    gl.getExtension('WEBGL_lose_context')?.loseContext();
  }
}

/** Float RGBA -> 8-bit RGB in one pass: floor(clamp(v, 0, 1) * 255 + 0.5) in float32, NaN -> 0 (sdk/image.py
 * `to_uint8`). */
function rgbUint8(rgba) {
  const rgb = new Uint8Array((rgba.length / 4) * 3);
  for (let i = 0, j = 0; i < rgba.length; i += 4, j += 3) {
    for (let c = 0; c < 3; c++) {
      const value = rgba[i + c];
      const v = value > 0 ? (value < 1 ? value : 1) : 0; // NaN -> 0
      rgb[j + c] = Math.floor(Math.fround(Math.fround(v * 255) + 0.5));
    }
  }
  return rgb;
}

/** RGBA -> RGB (rows unchanged: read-back row 0 is the top image row, docs/porting.md 3.5 "Orientation"). */
function dropAlpha(rgba, Type) {
  const rgb = new Type((rgba.length / 4) * 3);
  for (let i = 0, j = 0; i < rgba.length; i += 4, j += 3) {
    rgb[j] = rgba[i];
    rgb[j + 1] = rgba[i + 1];
    rgb[j + 2] = rgba[i + 2];
  }
  return rgb;
}
