// A capture folder, dropped on the page or chosen with the folder picker, collected as files
// with their paths and sent as they are: the page reads no camera file itself. The server's
// readers (transforms.json, LLFF poses_bounds.npy, COLMAP text) parse them at POST /v1/captures.

/** What a capture needs: images and camera files. Anything else (videos, archives) stays home. */
const CAPTURE_FILE = /\.(png|jpe?g|json|npy|txt)$/i;

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

/**
 * The capture's multipart body, as a function (a re-upload needs a fresh one): one part
 * `file` per file, its filename the path inside the capture folder (`images/0001.png`,
 * `sparse/0/cameras.txt`). Hidden files and files a capture cannot need are left out.
 */
export function captureForm(entries) {
  const kept = entries.filter(({ path }) => CAPTURE_FILE.test(path) && !path.split('/').some((p) => p.startsWith('.')));
  const root = commonFolder(kept.map((e) => e.path));
  const form = () => {
    const f = new FormData();
    for (const { file, path } of kept) f.append('file', file, path.slice(root.length));
    return f;
  };
  const bytes = kept.reduce((sum, { file }) => sum + file.size, 0);
  return { form, count: kept.length, bytes, name: root.replace(/\/$/, '') };
}
