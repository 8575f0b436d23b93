// A capture folder, dropped on the page or chosen with the folder picker, collected as files
// with their paths. The page reads no camera file and keeps no rule of its own about captures:
// the server says what to send (POST /v1/captures/plan: which files, which image set, the size
// each image is resized to first), and its readers parse the files at POST /v1/captures.

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

/** The size of an image as displayed (EXIF orientation applied), as the server reads it. */
async function imageSize(file, path) {
  let bitmap;
  try {
    bitmap = await createImageBitmap(file);
  } catch (e) {
    throw new Error(`${path}: the browser cannot read this image's size (${e.message}).`);
  }
  const size = { width: bitmap.width, height: bitmap.height };
  bitmap.close();
  return size;
}

/**
 * `file` resized to `resize.to` in its own format, when its size is `resize.from` (the size the
 * plan was made with); as it is otherwise (the server fits it).
 */
async function resized(file, path, { from, to }) {
  const { width, height } = await imageSize(file, path);
  if (width !== from.width || height !== from.height) return file;
  const bitmap = await createImageBitmap(file, { resizeWidth: to.width, resizeHeight: to.height, resizeQuality: 'high' });
  const canvas = new OffscreenCanvas(to.width, to.height);
  canvas.getContext('2d').drawImage(bitmap, 0, 0);
  bitmap.close();
  // JPEG stays JPEG (by its bytes, as the server re-encodes), anything else becomes PNG.
  const head = new Uint8Array(await file.slice(0, 3).arrayBuffer());
  const type = head[0] === 0xff && head[1] === 0xd8 && head[2] === 0xff ? 'image/jpeg' : 'image/png';
  return new File([await canvas.convertToBlob({ type, quality: 0.95 })], file.name, { type });
}

/**
 * The capture's multipart body, as a function (a re-upload needs a fresh one): one part `file`
 * per file, its filename the path inside the capture folder (`images/0001.png`,
 * `sparse/0/cameras.txt`). Which files go is the server's plan (`api.planCapture`): the page
 * sends the listing, then, when the server asks, the size of the images it names (one a folder
 * of images), and sends the files the plan names, each image resized here first when the plan
 * says so. `note` is the plan's notes (the set picked, the images resized, files left out).
 */
export async function captureForm(entries, api) {
  const root = commonFolder(entries.map((e) => e.path));
  const listed = entries.map((e) => ({ file: e.file, path: e.path.slice(root.length) }));
  const files = new Map(listed.map((e) => [e.path, e.file]));
  const listing = { files: listed.map((e) => e.path) };
  let { body: plan } = await api.planCapture(listing);
  if (plan.sizes_needed.length) {
    listing.sizes = await Promise.all(plan.sizes_needed.map(async (path) => ({ path, ...(await imageSize(files.get(path), path)) })));
    ({ body: plan } = await api.planCapture(listing));
  }
  if (plan.sizes_needed.length) throw new Error(`The server still asks for the sizes of ${plan.sizes_needed.slice(0, 3).join(', ')}.`);
  const kept = await Promise.all(
    plan.send.map(async ({ path, resize }) => ({ path, file: resize ? await resized(files.get(path), path, resize) : files.get(path) })),
  );
  const form = () => {
    const f = new FormData();
    for (const { file, path } of kept) f.append('file', file, path);
    return f;
  };
  const bytes = kept.reduce((sum, { file }) => sum + file.size, 0);
  return { form, count: kept.length, bytes, name: root.replace(/\/$/, ''), imageSet: plan.image_set, note: plan.notes.join('; ') };
}
