// The scene being viewed, uploaded to the server: the example (its files served by the server
// from --viewer-example, posted to POST /v1/scenes) or a capture (its files posted to
// POST /v1/captures, where the server's camera readers parse them).
//
// A scene: {id, label, cameras (API JSON), names, near, far, base (the camera whose size and lens
// the virtual camera uses), start (its first pose), upload(api, signal) -> new id}.

import { ApiError } from './api.js';
import { poseOf } from './camera.js';

/** Where the server serves the example's request.json and source_N.png. */
const EXAMPLE = '/viewer/example/';

/** The example's scene request: its sources' cameras and depth range, without the target, for `model` (null: the default). */
function sceneRequest(request, model) {
  const body = { sources: request.sources.map((s) => ({ camera: s.camera })), near: request.near, far: request.far };
  if (request.background) body.background = request.background;
  if (model) body.model = model;
  return body;
}

/** Fetches the example, uploads it through the scenes API and returns the scene. */
export async function exampleScene(api, signal) {
  const { body: request } = await api.json(`Reading the example (GET ${EXAMPLE}request.json)`, `${EXAMPLE}request.json`);
  const names = request.sources.map((_, i) => `source_${i}.png`);
  const images = await Promise.all(names.map((name) => api.blob(`Reading the example (GET ${EXAMPLE}${name})`, EXAMPLE + name)));
  // Built at each upload: a model chosen since goes with it.
  const form = (api) => {
    const f = new FormData();
    f.append('request', new Blob([JSON.stringify(sceneRequest(request, api.modelName))], { type: 'application/json' }), 'request.json');
    images.forEach((image, i) => f.append(`source_${i}`, image, names[i]));
    return f;
  };
  const upload = async (api, signal) => (await api.createScene(form(api), signal)).body.scene_id;
  return {
    id: await upload(api, signal),
    label: 'the example scene',
    cameras: request.sources.map((s) => s.camera),
    names,
    near: request.near,
    far: request.far,
    // The example's target is a held-out view: the page opens there.
    base: request.target,
    start: poseOf(request.target),
    upload,
  };
}

/** Checks that POST /v1/captures answered what the page needs (docs/viewer.md). */
function checkCaptureAnswer(body) {
  const missing = ['scene_id', 'cameras', 'near', 'far'].filter((k) => body?.[k] === undefined);
  if (missing.length || !Array.isArray(body.cameras) || body.cameras.length === 0) {
    throw new ApiError(`Uploading the capture failed: the server's answer lacks ${missing.join(', ') || 'cameras'}.`);
  }
}

/** Uploads a capture (`form()` builds its multipart body) and returns the scene. */
export async function captureScene(api, form, label, signal) {
  const { body } = await api.createCaptureScene(form(), signal);
  checkCaptureAnswer(body);
  return {
    id: body.scene_id,
    label,
    cameras: body.cameras,
    names: body.names ?? body.cameras.map((_, i) => `view ${i + 1}`),
    near: body.near,
    far: body.far,
    base: body.cameras[0],
    start: poseOf(body.cameras[0]),
    upload: async (api, signal) => (await api.createCaptureScene(form(), signal)).body.scene_id,
  };
}
