// A rendered view as the server sends it (JSON: base64 PNG rgb, base64 little-endian float32
// depth and opacity), decoded, and drawn on a canvas as RGB, colour-mapped depth or opacity.

function bytesOf(base64) {
  const text = atob(base64);
  const bytes = new Uint8Array(text.length);
  for (let i = 0; i < text.length; i++) bytes[i] = text.charCodeAt(i);
  return bytes;
}

/** Read as little-endian whatever the machine's byte order (the API's `byte_order`). */
function floatsOf(image) {
  const view = new DataView(bytesOf(image.data).buffer);
  const values = new Float32Array(view.byteLength / 4);
  for (let i = 0; i < values.length; i++) values[i] = view.getFloat32(4 * i, true);
  return values;
}

/** `{width, height, rgb: ImageBitmap, depth, opacity: Float32Array}` of a JSON render response. */
export async function decodeView(body) {
  const rgb = await createImageBitmap(new Blob([bytesOf(body.rgb.data)], { type: 'image/png' }));
  return { width: body.width, height: body.height, rgb, depth: floatsOf(body.depth), opacity: floatsOf(body.opacity) };
}

/** Turbo colour map (Google's polynomial fit), t in [0, 1] -> [r, g, b] in [0, 1]. */
function turbo(t) {
  const x = Math.min(1, Math.max(0, t));
  const p = (c) => c[0] + x * (c[1] + x * (c[2] + x * (c[3] + x * (c[4] + x * c[5]))));
  const clamp = (v) => Math.min(1, Math.max(0, v));
  return [
    clamp(p([0.13572138, 4.6153926, -42.66032258, 132.13108234, -152.94239396, 59.28637943])),
    clamp(p([0.09140261, 2.19418839, 4.84296658, -14.18503333, 4.27729857, 2.82956604])),
    clamp(p([0.1066733, 12.64194608, -60.58204836, 110.36276771, -89.90310912, 27.34824973])),
  ];
}

/** Depth's colour range: over pixels that are mostly opaque (elsewhere depth means little). */
function depthRange(view) {
  let lo = Infinity;
  let hi = -Infinity;
  const consider = (minOpacity) => {
    view.depth.forEach((d, i) => {
      if (view.opacity[i] >= minOpacity && Number.isFinite(d)) {
        lo = Math.min(lo, d);
        hi = Math.max(hi, d);
      }
    });
  };
  consider(0.5);
  if (lo > hi) consider(0);
  if (lo > hi) return { lo: 0, hi: 1 };
  return { lo, hi: hi > lo ? hi : lo + 1e-6 };
}

/** One RGBA pixel per value: `colour(i)` -> [r, g, b] in [0, 1]. */
function pixels(ctx, view, colour) {
  const image = ctx.createImageData(view.width, view.height);
  for (let i = 0; i < view.width * view.height; i++) {
    const [r, g, b] = colour(i);
    image.data.set([r * 255, g * 255, b * 255, 255], 4 * i);
  }
  ctx.putImageData(image, 0, 0);
}

/**
 * Draws `view` on `canvas` at its own size in `mode` (rgb, depth, opacity); returns the depth
 * range shown (depth mode) or null. Depth is dimmed by opacity: empty space shows black.
 */
export function drawView(canvas, view, mode) {
  canvas.width = view.width;
  canvas.height = view.height;
  const ctx = canvas.getContext('2d');
  if (mode === 'opacity') {
    pixels(ctx, view, (i) => Array(3).fill(view.opacity[i]));
    return null;
  }
  if (mode === 'depth') {
    const range = depthRange(view);
    pixels(ctx, view, (i) => turbo((view.depth[i] - range.lo) / (range.hi - range.lo)).map((c) => c * view.opacity[i]));
    return range;
  }
  ctx.drawImage(view.rgb, 0, 0);
  return null;
}

/** The colour bar of the depth legend. */
export function drawColourBar(canvas) {
  const ctx = canvas.getContext('2d');
  for (let x = 0; x < canvas.width; x++) {
    const [r, g, b] = turbo(x / (canvas.width - 1));
    ctx.fillStyle = `rgb(${r * 255}, ${g * 255}, ${b * 255})`;
    ctx.fillRect(x, 0, 1, canvas.height);
  }
}
