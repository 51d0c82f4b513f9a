// A bundle's reference clip in the page (sdk/reference_clip.py's ReferenceClip; docs/compositing.md): the original
// video frames I_ori (one H.264 picture per entry, intra-only or in groups of `gop` pictures, decoded with WebCodecs),
// the facial masks M (one 8-bit grey PNG per entry, decoded by the browser's image decoder, or the luma plane of an
// H.264 picture), and the camera that aligns the head with them.
//
// H.264 decoding is exact, but the page converts the 4:2:0 picture to RGB itself (the BT.601 or BT.709 matrix the
// stream's colour tags name, nearest chroma), where the Python runtime uses libswscale: the RGB differs by up to 3
// levels (45.7 dB on a noisy test picture; docs/web.md "Composited frames"). Masks decode exactly. A frame or mask at
// another output size is area-averaged, where Python uses swscale's area filter (close, not bit for bit).
//
// A clip in groups of pictures is decoded a group at a time, as Python's GroupDecoder does: the group a frame falls
// in is decoded from its keyframe and its converted pictures are held until another group is asked for.

import { BundleError } from './bundle.js';
import { Camera } from './camera.js';

const FRAME_CODECS = ['h264'];
const MASK_CODECS = ['png', 'h264'];
const MAX_CLIP_FRAMES = 100000;
const MASK_LEVELS = 255;
// Y'CbCr -> R'G'B' for limited-range 8-bit video: the luma and chroma gains of each matrix (R = y + rv v, G = y - gu
// u - gv v, B = y + bu u, with y = (Y - 16) 255/219 and u, v = (C - 128) 255/224).
const MATRICES = {
  bt470bg: { rv: 1.402, gu: 0.344136, gv: 0.714136, bu: 1.772 },
  smpte170m: { rv: 1.402, gu: 0.344136, gv: 0.714136, bu: 1.772 },
  bt709: { rv: 1.5748, gu: 0.187324, gv: 0.468124, bu: 1.8556 },
};

const frameEntry = (index) => `reference/frame/${String(index).padStart(5, '0')}`;
const maskEntry = (index) => `reference/mask/${String(index).padStart(5, '0')}`;

/** The codec string WebCodecs wants for an Annex B H.264 picture: avc1.PPCCLL from its first SPS. */
function avcCodec(data, where) {
  for (let i = 0; i + 7 < data.length; i++) {
    if (data[i] === 0 && data[i + 1] === 0 && data[i + 2] === 1 && (data[i + 3] & 31) === 7) {
      const hex = (b) => b.toString(16).padStart(2, '0');
      return `avc1.${hex(data[i + 4])}${hex(data[i + 5])}${hex(data[i + 6])}`;
    }
  }
  throw new BundleError(`${where} is not an H.264 picture with its parameter sets (no SPS)`);
}

/** One group of H.264 pictures (a keyframe with its parameter sets, then the pictures predicted from it) -> one
 * VideoFrame per entry, in order (a fresh decoder, flushed: nothing shared between groups). `wheres` names each
 * entry for errors. */
async function decodeGroup(chunks, wheres) {
  const where = wheres[0];
  if (typeof VideoDecoder === 'undefined') {
    throw new BundleError(`${where}: this browser has no WebCodecs VideoDecoder (a secure context is needed)`);
  }
  const pictures = [];
  let failure = null;
  const decoder = new VideoDecoder({ output: (frame) => pictures.push(frame), error: (error) => { failure = error; } });
  try {
    decoder.configure({ codec: avcCodec(chunks[0], where), optimizeForLatency: true });
    chunks.forEach((data, i) => {
      if (!data.length) throw new BundleError(`${wheres[i]} is empty`);
      decoder.decode(new EncodedVideoChunk({ type: i === 0 ? 'key' : 'delta', timestamp: i, data }));
    });
    await decoder.flush();
  } catch (error) {
    failure = failure ?? error;
  } finally {
    if (decoder.state !== 'closed') decoder.close();
  }
  if (failure || pictures.length !== chunks.length) {
    pictures.forEach((p) => p.close());
    const which = failure ? where : wheres[Math.min(pictures.length, wheres.length - 1)];
    throw new BundleError(`${which} is not decodable as H.264: ${failure?.message ?? `${pictures.length} pictures `
      + `for ${chunks.length} entries`}`);
  }
  return pictures;
}

/** Random access to a stream stored in groups of `gop` pictures (Python's GroupDecoder): the group an index falls
 * in is decoded once, each picture converted by `convert(picture, index)` (awaited), and held until another group
 * is asked for. Calls made while a group decodes wait for it. */
class GroupDecoder {
  constructor(count, gop, decode, convert) {
    Object.assign(this, { count, gop, decode, convert, group: -1, held: null });
  }

  async get(index) {
    const group = Math.floor(index / this.gop);
    if (group !== this.group) {
      this.group = group;
      this.held = this._decodeGroup(group);
      this.held.catch(() => { if (this.group === group) this.group = -1; });
    }
    return (await this.held)[index - group * this.gop];
  }

  async _decodeGroup(group) {
    const first = group * this.gop;
    const indices = Array.from({ length: Math.min(this.count, first + this.gop) - first }, (_, i) => first + i);
    const pictures = await this.decode(indices);
    try {
      const converted = [];
      for (let i = 0; i < indices.length; i++) converted.push(await this.convert(pictures[i], indices[i]));
      return converted;
    } finally {
      pictures.forEach((p) => p?.close?.());
    }
  }
}

/** A decoded 4:2:0 VideoFrame -> RGB Uint8Array [h * w * 3], limited range, by its colour matrix. */
async function pictureRgb(picture, where) {
  const { format } = picture;
  const width = picture.visibleRect.width;
  const height = picture.visibleRect.height;
  if (format !== 'I420') throw new BundleError(`${where} must be 4:2:0 (I420), got ${format}`);
  const planes = new Uint8Array(picture.allocationSize({ rect: picture.visibleRect }));
  const layout = await picture.copyTo(planes, { rect: picture.visibleRect });
  const space = picture.colorSpace ?? {};
  const m = MATRICES[space.matrix ?? 'bt470bg'] ?? MATRICES.bt470bg;
  const full = Boolean(space.fullRange);
  const [yPlane, uPlane, vPlane] = layout;
  const rgb = new Uint8Array(width * height * 3);
  const ys = full ? 1 : 255 / 219;
  const cs = full ? 1 : 255 / 224;
  const y0 = full ? 0 : 16;
  const clamp = (v) => (v < 0 ? 0 : v > 255 ? 255 : Math.floor(v + 0.5));
  for (let row = 0; row < height; row++) {
    const yRow = yPlane.offset + row * yPlane.stride;
    const cRow = (row >> 1);
    for (let col = 0; col < width; col++) {
      const y = (planes[yRow + col] - y0) * ys;
      const c = cRow * uPlane.stride + (col >> 1);
      const u = (planes[uPlane.offset + c] - 128) * cs;
      const v = (planes[vPlane.offset + cRow * vPlane.stride + (col >> 1)] - 128) * cs;
      const o = 3 * (row * width + col);
      rgb[o] = clamp(y + m.rv * v);
      rgb[o + 1] = clamp(y - m.gu * u - m.gv * v);
      rgb[o + 2] = clamp(y + m.bu * u);
    }
  }
  return { rgb, width, height };
}

/** An 8-bit grey PNG -> its levels Uint8Array [h * w] (the browser's decoder, no colour conversion). */
async function maskLevels(data, where) {
  let bitmap;
  try {
    bitmap = await createImageBitmap(new Blob([data], { type: 'image/png' }),
      { colorSpaceConversion: 'none', premultiplyAlpha: 'none' });
  } catch (error) {
    throw new BundleError(`${where} is not decodable as PNG: ${error?.message ?? error}`);
  }
  const { width, height } = bitmap;
  const canvas = new OffscreenCanvas(width, height);
  const context = canvas.getContext('2d', { willReadFrequently: true });
  context.drawImage(bitmap, 0, 0);
  bitmap.close();
  const rgba = context.getImageData(0, 0, width, height).data;
  const levels = new Uint8Array(width * height);
  for (let i = 0; i < levels.length; i++) {
    if (rgba[4 * i] !== rgba[4 * i + 1] || rgba[4 * i] !== rgba[4 * i + 2]) {
      throw new BundleError(`${where} must be an 8-bit grey image, got colour pixels`);
    }
    levels[i] = rgba[4 * i];
  }
  return { levels, width, height };
}

/** An H.264 mask's decoded 4:2:0 VideoFrame -> its levels Uint8Array [h * w]: the luma plane as it is. */
async function lumaLevels(picture, where) {
  if (picture.format !== 'I420') throw new BundleError(`${where} must be 4:2:0 (I420), got ${picture.format}`);
  const width = picture.visibleRect.width;
  const height = picture.visibleRect.height;
  const planes = new Uint8Array(picture.allocationSize({ rect: picture.visibleRect }));
  const [yPlane] = await picture.copyTo(planes, { rect: picture.visibleRect });
  const levels = new Uint8Array(width * height);
  for (let row = 0; row < height; row++) {
    levels.set(planes.subarray(yPlane.offset + row * yPlane.stride, yPlane.offset + row * yPlane.stride + width),
      row * width);
  }
  return { levels, width, height };
}

/** `channels`-channel pixels [h * w * c] resized to w2 x h2 by area averaging (each output pixel the mean of the
 * input area it covers, partial pixels weighted). Returns Float64Array. */
export function areaResized(pixels, width, height, channels, newWidth, newHeight) {
  const weights = (size, newSize) => {
    const scale = size / newSize;
    const out = [];
    for (let o = 0; o < newSize; o++) {
      const lo = o * scale;
      const hi = lo + scale;
      const taps = [];
      for (let i = Math.floor(lo); i < Math.min(size, Math.ceil(hi)); i++) {
        const w = Math.min(hi, i + 1) - Math.max(lo, i);
        if (w > 0) taps.push([i, w / scale]);
      }
      out.push(taps);
    }
    return out;
  };
  const xs = weights(width, newWidth);
  const ys = weights(height, newHeight);
  const out = new Float64Array(newWidth * newHeight * channels);
  for (let oy = 0; oy < newHeight; oy++) {
    for (let ox = 0; ox < newWidth; ox++) {
      for (const [iy, wy] of ys[oy]) {
        for (const [ix, wx] of xs[ox]) {
          const w = wy * wx;
          const src = (iy * width + ix) * channels;
          const dst = (oy * newWidth + ox) * channels;
          for (let c = 0; c < channels; c++) out[dst + c] += w * pixels[src + c];
        }
      }
    }
  }
  return out;
}

export class ReferenceClip {
  constructor(fields) {
    Object.assign(this, fields);
  }

  /** The bundle's clip (manifest 'reference'), output at `size` ([w, h]; default the clip's own): every entry
   * present, frame 0 and mask 0 decoded, so a clip the page cannot play fails at load. BundleError otherwise. */
  static async open(bundle, size = null) {
    const layout = bundle.manifest.reference;
    const where = `${bundle.name}: manifest 'reference'`;
    if (layout === null || typeof layout !== 'object') throw new BundleError(`${where} is not an object`);
    const { count } = layout;
    if (!(Number.isInteger(count) && count >= 1 && count <= MAX_CLIP_FRAMES)) {
      throw new BundleError(`${where}: count must be an integer in 1..${MAX_CLIP_FRAMES}, got ${count}`);
    }
    const maskCodec = layout.mask_codec ?? 'png';
    if (!FRAME_CODECS.includes(layout.frame_codec ?? 'h264') || !MASK_CODECS.includes(maskCodec)) {
      throw new BundleError(`${where}: codecs ${layout.frame_codec}/${layout.mask_codec}; the page plays h264 `
        + `frames and ${MASK_CODECS.join(' or ')} masks`);
    }
    const gop = layout.gop ?? 1;
    if (!(Number.isInteger(gop) && gop >= 1 && gop <= MAX_CLIP_FRAMES)) {
      throw new BundleError(`${where}: gop must be an integer in 1..${MAX_CLIP_FRAMES}, got ${gop}`);
    }
    let camera;
    try {
      camera = Camera.fromDict(layout.camera);
    } catch (error) {
      throw new BundleError(`${where}: camera is invalid: ${error.message}`);
    }
    for (let i = 0; i < count; i++) {
      for (const name of [frameEntry(i), maskEntry(i)]) {
        if (!bundle.hasBuffer(name)) {
          throw new BundleError(`${bundle.name}: reference clip of ${count} frames lacks entry '${name}'`);
        }
      }
    }
    const [width, height] = size ?? [camera.width, camera.height];
    const clip = new ReferenceClip({ bundle, count, camera, clipSize: [camera.width, camera.height],
      size: [width, height], maskCodec });
    const label = (kind) => (i) => `${bundle.name}: reference ${kind} ${i}`;
    const h264 = (entry, kind) => (indices) => decodeGroup(indices.map((i) => clip._bytes(entry(i))),
      indices.map(label(kind)));
    clip._frames = new GroupDecoder(count, gop, h264(frameEntry, 'frame'),
      (picture, i) => clip._frameRgb(picture, label('frame')(i)));
    clip._masks = maskCodec === 'h264'
      ? new GroupDecoder(count, gop, h264(maskEntry, 'mask'),
        async (picture, i) => clip._maskLevels(await lumaLevels(picture, label('mask')(i)), label('mask')(i)))
      : new GroupDecoder(count, 1, async (indices) => [await maskLevels(clip._bytes(maskEntry(indices[0])),
        label('mask')(indices[0]))], (levels, i) => clip._maskLevels(levels, label('mask')(i)));
    await clip.frame(0);
    await clip.mask(0);
    return clip;
  }

  /** The camera aligning the head with the clip, at the output size. */
  get outputCamera() {
    const [w, h] = this.size;
    return w === this.camera.width && h === this.camera.height ? this.camera : this.camera.resized(w, h);
  }

  _bytes(name) {
    return this.bundle.buffer(name).data;
  }

  _index(index) {
    if (!(Number.isInteger(index) && index >= 0 && index < this.count)) {
      throw new BundleError(`reference frame index ${index} is outside 0..${this.count - 1}`);
    }
    return index;
  }

  _checkSize(width, height, where) {
    const [w, h] = this.clipSize;
    if (width !== w || height !== h) throw new BundleError(`${where} is ${width}x${height}, the clip is ${w}x${h}`);
  }

  /** Original frame `index`: Uint8Array RGB [h * w * 3] at the output size (held for the next call: do not
   * change it). */
  async frame(index) {
    return this._frames.get(this._index(index));
  }

  /** Facial mask `index`: Float32Array [h * w] in [0, 1] (its levels / 255) at the output size. */
  async mask(index) {
    const resized = await this._masks.get(this._index(index));
    const out = new Float32Array(resized.length);
    for (let i = 0; i < out.length; i++) out[i] = Math.fround(resized[i] / MASK_LEVELS);
    return out;
  }

  async _frameRgb(picture, where) {
    const decoded = await pictureRgb(picture, where);
    this._checkSize(decoded.width, decoded.height, where);
    return this._resized(decoded.rgb, 3, (v) => Math.floor(v + 0.5), Uint8Array);
  }

  _maskLevels({ levels, width, height }, where) {
    this._checkSize(width, height, where);
    return this._resized(levels, 1, (v) => Math.floor(v + 0.5), Uint8Array);
  }

  _resized(pixels, channels, round, Type) {
    const [w, h] = this.size;
    const [cw, ch] = this.clipSize;
    if (w === cw && h === ch) return pixels;
    return Type.from(areaResized(pixels, cw, ch, channels, w, h), round);
  }
}
