// A capture folder, dropped on the page or chosen with the folder picker, collected as files
// with their paths and sent as they are: the page reads no camera file itself. The server's
// readers (transforms.json, LLFF poses_bounds.npy, COLMAP text) parse them at POST /v1/captures.

/** What a capture needs: images and camera files. Anything else (videos, archives) stays home. */
const CAPTURE_FILE = /\.(png|jpe?g|json|npy|txt)$/i;
const IMAGE_FILE = /\.(png|jpe?g)$/i;
/** The image sets LLFF, nerfstudio and COLMAP keep beside each other: images/, images_N/. */
const SET_FOLDER = /^images(?:_([1-9][0-9]*))?$/;

function fileOf(entry) {
  return new Promise((resolve, reject) => entry.file(resolve, reject));
}

function readBatch(reader) {
  return new Promise((resolve, reject) => reader.readEntries(resolve, reject));
}

/** Adds the files under a dropped file-system entry to `out`, with paths from the drop. */
async function walk(entry, out) {
  if (entry.isFile) {
    out.push({ file: await fileOf(entry), path: entry.fullPath.replace(/^\/+/, '') });
    return;
  }
  const reader = entry.createReader();
  // readEntries answers in batches until an empty one.
  for (let batch = await readBatch(reader); batch.length; batch = await readBatch(reader)) {
    for (const child of batch) await walk(child, out);
  }
}

/**
 * The files of a drop, folders walked. The entries are taken before the first await: a drop's
 * DataTransfer is emptied when its event handler returns.
 */
export async function filesFromDrop(dataTransfer) {
  const entries = [...dataTransfer.items].map((item) => item.webkitGetAsEntry?.()).filter(Boolean);
  if (entries.length === 0) return [...dataTransfer.files].map((file) => ({ file, path: file.name }));
  const out = [];
  for (const entry of entries) await walk(entry, out);
  return out;
}

/** The files chosen with `<input type=file webkitdirectory>`. */
export function filesFromPicker(fileList) {
  return [...fileList].map((file) => ({ file, path: file.webkitRelativePath || file.name }));
}

/** The folder every path starts with ("capture/"), or "" when they do not share one. */
function commonFolder(paths) {
  const first = paths[0]?.split('/')[0] ?? '';
  const shared = paths.length > 0 && paths.every((p) => p.includes('/') && p.split('/')[0] === first);
  return shared ? `${first}/` : '';
}

/** The image sets at the capture's root: factor (1 for images/) -> its image entries, by path. */
function imageSets(entries) {
  const sets = new Map();
  for (const entry of entries) {
    const parts = entry.path.split('/');
    const m = parts.length === 2 && IMAGE_FILE.test(parts[1]) ? SET_FOLDER.exec(parts[0]) : null;
    const factor = m ? Number(m[1] ?? 1) : 0;
    if (factor === 1 && m[1] !== undefined) continue; // images_1 is no set
    if (factor) sets.set(factor, [...(sets.get(factor) ?? []), entry]);
  }
  for (const list of sets.values()) list.sort((a, b) => (a.path < b.path ? -1 : 1));
  return new Map([...sets].sort(([a], [b]) => a - b));
}

async function imageSize(file) {
  const bitmap = await createImageBitmap(file);
  const size = { width: bitmap.width, height: bitmap.height };
  bitmap.close();
  return size;
}

/** `file` within `maxPixels` (aspect kept), in its own format; null when it fits already. */
async function shrunk(file, maxPixels) {
  const { width, height } = await imageSize(file);
  if (width * height <= maxPixels) return null;
  const scale = Math.sqrt(maxPixels / (width * height));
  const [w, h] = [Math.max(1, Math.floor(width * scale)), Math.max(1, Math.floor(height * scale))];
  const bitmap = await createImageBitmap(file, { resizeWidth: w, resizeHeight: h, resizeQuality: 'high' });
  const canvas = new OffscreenCanvas(w, h);
  canvas.getContext('2d').drawImage(bitmap, 0, 0);
  bitmap.close();
  const type = /\.jpe?g$/i.test(file.name) ? 'image/jpeg' : 'image/png';
  return { file: new File([await canvas.convertToBlob({ type, quality: 0.95 })], file.name, { type }), from: [width, height], to: [w, h] };
}

/**
 * The capture's multipart body, as a function (a re-upload needs a fresh one): one part `file`
 * per file, its filename the path inside the capture folder (`images/0001.png`,
 * `sparse/0/cameras.txt`). Hidden files and files a capture cannot need are left out. Of the
 * image sets only one is sent: the largest within the server's `max_source_pixels` (the server's
 * readers pick the same from what they get, and scale the cameras to it); when none fits, or the
 * capture keeps no sets, images beyond the limit are resized here. `note` says what was done.
 */
export async function captureForm(entries, limits) {
  let kept = entries.filter(({ path }) => CAPTURE_FILE.test(path) && !path.split('/').some((p) => p.startsWith('.')));
  const root = commonFolder(kept.map((e) => e.path));
  kept = kept.map((e) => ({ file: e.file, path: e.path.slice(root.length) }));
  const sets = imageSets(kept);
  const maxPixels = limits.max_source_pixels;
  let imageSet = null;
  let fits = false;
  if (sets.size) {
    const sizes = new Map();
    for (const [factor, list] of sets) sizes.set(factor, await imageSize(list[0].file));
    const fitting = [...sets.keys()].find((f) => sizes.get(f).width * sizes.get(f).height <= maxPixels);
    imageSet = fitting ?? Math.max(...sets.keys());
    fits = fitting !== undefined;
    const others = new Set([...sets].filter(([f]) => f !== imageSet).flatMap(([, list]) => list));
    kept = kept.filter((e) => !others.has(e));
  }
  let note = '';
  if (!fits) {
    const resized = [];
    kept = await Promise.all(
      kept.map(async (e) => {
        const r = IMAGE_FILE.test(e.path) ? await shrunk(e.file, maxPixels) : null;
        if (r) resized.push(r);
        return r ? { file: r.file, path: e.path } : e;
      }),
    );
    // the line the scnerf client and the server say (scnerf_capture::upload::fit_to_limit)
    if (resized.length) note = `${resized.length} images of ${resized[0].from.join('x')} exceed the server's limit of ${maxPixels} pixels per source view: resizing them to ${resized[0].to.join('x')}`;
  }
  const form = () => {
    const f = new FormData();
    for (const { file, path } of kept) f.append('file', file, path);
    return f;
  };
  const bytes = kept.reduce((sum, { file }) => sum + file.size, 0);
  const setName = imageSet === null ? null : imageSet === 1 ? 'images' : `images_${imageSet}`;
  return { form, count: kept.length, bytes, name: root.replace(/\/$/, ''), imageSet: setName, note };
}
