// The viewer page: opens the example scene, renders the virtual camera coarse to fine as it
// moves, and shows what the server answers (the sources it used, its timings, its errors).

import { Api } from './api.js';
import { cameraAt, intrinsicsOf, nerfstudioPath, poseOf, sceneFrame, viewFrom } from './camera.js';
import { captureForm, filesFromDrop, filesFromPicker } from './capture.js';
import { attachControls } from './controls.js';
import { decodeView, drawColourBar, drawView } from './images.js';
import { Overview } from './overview.js';
import { Progressive } from './progressive.js';
import { captureScene, exampleScene } from './scene.js';

const $ = (id) => document.getElementById(id);

/** Render sizes as fractions of the scene camera's, coarse first, with their names. */
const SIZES = [
  [1 / 16, '1/16'],
  [1 / 8, '1/8'],
  [1 / 4, '1/4'],
  [1 / 2, '1/2'],
  [1, 'full'],
];
/** The first size asked for after a move: small enough to come back in seconds on a CPU. */
const DEFAULT_COARSEST = 1 / 8;
/** Finer than this, a paper-size model takes about a minute per view on a 2-core CPU. */
const DEFAULT_FINEST = 1 / 2;
const TOKEN_KEY = 'scnerf-viewer-token';
/** Frames per second of a recorded camera path: the camera is sampled this often while it moves. */
const PATH_FPS = 24;
/** Tells this tab's requests apart in the server's logs (sent as x-request-id). */
const PAGE_ID = Math.random().toString(16).slice(2, 8);

const canvas = $('view');
const api = new Api(() => $('token').value.trim());
/** scene: the uploaded scene; geometry: its centre, up and radius; view: the virtual camera; shown: the last render. */
const state = { scene: null, geometry: null, view: null, shown: null, mode: 'rgb', requests: 0 };

function setStatus(text, phase) {
  $('status').textContent = text;
  canvas.dataset.state = phase;
}

function showError(error) {
  $('error').textContent = error.message;
  $('error').hidden = false;
}

function clearError() {
  $('error').hidden = true;
}

function sizeOf(fraction) {
  const base = state.scene.base;
  return `${Math.max(1, Math.round(base.width * fraction))}×${Math.max(1, Math.round(base.height * fraction))}`;
}

function sizeLabel(fraction) {
  return `${SIZES.find(([f]) => f === fraction)[1]} (${sizeOf(fraction)})`;
}

/**
 * The steps to render after a move, coarse first, from the chosen coarsest size to the chosen
 * finest, each sampled the server's default way (guided when the model has it: fast enough to follow a drag).
 */
function steps() {
  const [coarsest, finest] = [Number($('coarsest').value), Number($('finest').value)];
  return SIZES.map(([f]) => f)
    .filter((f) => f >= Math.min(coarsest, finest) && f <= finest)
    .map((fraction) => ({ fraction, sampling: null }));
}

/** The still: the finest size with every ray sampled in full (the paper's samples). */
function fullQualityStill() {
  if (state.view) progressive.restart(state.view, [{ fraction: Number($('finest').value), sampling: 'full' }]);
}

function stepLabel(step) {
  return `${sizeLabel(step.fraction)}${step.sampling === 'full' ? ' in full quality' : ''}`;
}

/** Source indices the server names (header or JSON field); for a 3-view scene all three. */
function sourcesOf(body, headers) {
  const header = headers.get('x-scnerf-sources');
  if (header) return header.split(',').map((s) => Number.parseInt(s, 10)).filter(Number.isInteger);
  if (Array.isArray(body.sources)) return body.sources;
  return state.scene.cameras.length === 3 ? [0, 1, 2] : null;
}

/** Renders on the scene, uploading it again once if the server forgot it (expired, evicted). */
async function renderScene(scene, target, requestId, signal, sampling) {
  try {
    return await api.render(scene.id, target, requestId, signal, sampling);
  } catch (e) {
    if (e.code !== 'scene_not_found') throw e;
    setStatus(`${scene.label} expired on the server: uploading it again…`, 'rendering');
    scene.id = await scene.upload(api, signal);
    return api.render(scene.id, target, `${requestId}-again`, signal, sampling);
  }
}

async function renderLevel(view, step, signal) {
  const scene = state.scene;
  const target = cameraAt(scene.base, view.pose, step.fraction);
  const requestId = `viewer-${PAGE_ID}-${++state.requests}`;
  const started = performance.now();
  const { body, headers } = await renderScene(scene, target, requestId, signal, step.sampling);
  const image = await decodeView(body);
  const roundTripMs = performance.now() - started;
  const sampling = { mode: body.sampling ?? 'not reported', samplesPerRay: body.samples_per_ray };
  return { ...image, step, requestId, roundTripMs, timings: body.timings_ms ?? {}, sources: sourcesOf(body, headers), sampling };
}

function redraw() {
  if (!state.shown) return;
  const range = drawView(canvas, state.shown, state.mode);
  $('legend').hidden = !range;
  if (range) $('legend-range').textContent = `Depth ${range.lo.toFixed(3)} (blue) to ${range.hi.toFixed(3)} (red); dark: empty space.`;
}

function describeSources(sources) {
  if (!sources) return 'not reported by the server';
  const names = sources.map((i) => `${i + 1} (${state.scene.names[i] ?? '?'})`);
  return `views ${names.join(', ')}`;
}

function describeSampling({ mode, samplesPerRay }) {
  return samplesPerRay == null ? mode : `${mode}, ${samplesPerRay.toFixed(1)} network samples per pixel`;
}

function showInfo(shown) {
  const rows = [
    ['Size', sizeLabel(shown.step.fraction)],
    ['Sampling', describeSampling(shown.sampling)],
    ['Sources', describeSources(shown.sources)],
    ['Round trip', `${shown.roundTripMs.toFixed(0)} ms`],
    ['Request id', shown.requestId],
  ];
  $('info').replaceChildren(...rows.flatMap(([k, v]) => [Object.assign(document.createElement('dt'), { textContent: k }), Object.assign(document.createElement('dd'), { textContent: v })]));
  const timingRows = Object.entries(shown.timings).map(([stage, ms]) => {
    const row = document.createElement('tr');
    row.append(Object.assign(document.createElement('th'), { textContent: stage, scope: 'row' }), Object.assign(document.createElement('td'), { textContent: `${ms.toFixed(1)} ms` }));
    return row;
  });
  $('timings').tBodies[0].replaceChildren(...timingRows);
}

function drawOverview() {
  overview.draw(state.view, state.scene.base, state.shown?.sources ?? []);
}

const progressive = new Progressive(renderLevel, {
  onStart: (step) => setStatus(`Rendering ${stepLabel(step)}…`, 'rendering'),
  onFrame: (shown) => {
    state.shown = shown;
    redraw();
    showInfo(shown);
    drawOverview();
    clearError();
    canvas.dataset.frames = String(Number(canvas.dataset.frames) + 1);
    canvas.dataset.requestId = shown.requestId;
    $('save').disabled = false;
  },
  onDone: () => setStatus(`Showing ${stepLabel(state.shown.step)}. Drag to move the camera.`, 'idle'),
  onBusy: (error, seconds) => setStatus(`${error.message} Retrying in ${seconds} s.`, 'rendering'),
  onError: (error) => {
    showError(error);
    setStatus('Rendering stopped by the error above. Move the camera to try again.', 'error');
  },
});

/** The camera moved: show it in the overview and render it (cancelling the last view's renders). */
function setView(view) {
  state.view = view;
  drawOverview();
  progressive.restart(view, steps());
}

function snap(i) {
  if (state.scene && i < state.scene.cameras.length) setView(viewFrom(poseOf(state.scene.cameras[i]), state.geometry));
}

function reset() {
  if (state.scene) setView(viewFrom(state.scene.start, state.geometry));
}

const overview = new Overview($('overview'), snap);

function fillViews() {
  const buttons = state.scene.names.map((name, i) => {
    const b = Object.assign(document.createElement('button'), { type: 'button', textContent: String(i + 1), title: name });
    b.setAttribute('aria-label', `View from camera ${i + 1} (${name})${i < 9 ? `, key ${i + 1}` : ''}`);
    b.addEventListener('click', () => snap(i));
    return b;
  });
  $('views').replaceChildren(...buttons);
}

/** The size selectors, labelled with the scene's pixel sizes; the choices made stay. */
function fillSizes() {
  for (const [id, fallback] of [['coarsest', DEFAULT_COARSEST], ['finest', DEFAULT_FINEST]]) {
    const chosen = Number($(id).value) || fallback;
    const options = SIZES.map(([f]) => Object.assign(document.createElement('option'), { value: String(f), textContent: sizeLabel(f), selected: f === chosen }));
    $(id).replaceChildren(...options);
  }
}

/** Uploads a scene with `load()` and views it; on failure the scene shown before stays. */
async function openScene(load, what, explain = (e) => e) {
  setStatus(`Uploading ${what}…`, 'uploading');
  try {
    const scene = await load();
    progressive.stop();
    state.scene = scene;
    state.geometry = sceneFrame(scene.cameras.map(poseOf), scene.near, scene.far);
    state.shown = null;
    overview.setScene(scene, state.geometry);
    fillViews();
    fillSizes();
    canvas.style.aspectRatio = `${scene.base.width} / ${scene.base.height}`;
    if (recording.timer !== null) toggleRecording(); // a path belongs to one scene's world
    clearError();
    reset();
  } catch (e) {
    showError(explain(e));
    setStatus(state.scene ? `Still showing ${state.scene.label}.` : 'No scene loaded.', 'error');
  }
}

function openExample() {
  return openScene(exampleScene.bind(null, api), 'the example scene', (e) =>
    e.status === 404 && e.code === 'not_found' ? new Error(`${e.message} This server has no example scene (see its --viewer-example flag): drop a capture folder instead.`) : e,
  );
}

/** Reads the server's limits, prepares the capture's files as the server plans them, then uploads it. */
async function openCapture(entries) {
  setStatus('Reading the capture…', 'uploading');
  let capture;
  try {
    const { body: limits } = await api.limits();
    capture = await captureForm(entries, api);
    if (capture.bytes > limits.max_capture_bytes) {
      const mb = (n) => (n / 2 ** 20).toFixed(1);
      throw new Error(`The capture is ${mb(capture.bytes)} MB, more than this server takes (${mb(limits.max_capture_bytes)} MB, its --max-capture-bytes): drop a smaller image set (images_N) or fewer images.`);
    }
  } catch (e) {
    showError(e);
    setStatus(state.scene ? `Still showing ${state.scene.label}.` : 'No scene loaded.', 'error');
    return;
  }
  const label = capture.name ? `the capture "${capture.name}"` : 'the dropped capture';
  const megabytes = (capture.bytes / 2 ** 20).toFixed(1);
  const set = capture.imageSet ? `, ${capture.imageSet}` : '';
  await openScene(() => captureScene(api, capture.form, label), `${label} (${capture.count} files${set}, ${megabytes} MB)`, (e) =>
    e.status === 404 && e.code === 'not_found' ? new Error('This server cannot parse captures yet: it has no POST /v1/captures (HTTP 404). Only the example scene can be viewed here.') : e,
  );
  $('capture-note').hidden = !(capture.note && state.scene?.label === label);
  $('capture-note').textContent = capture.note ? `${label}: ${capture.note}.` : '';
}

/** The flight being recorded: the virtual camera sampled PATH_FPS times a second while it moves. */
const recording = { cameras: [], timer: null, last: null };

function sampleFlight() {
  if (!state.view || state.view.pose === recording.last) return;
  recording.last = state.view.pose;
  recording.cameras.push(cameraAt(state.scene.base, state.view.pose, 1));
  $('path-status').textContent = `Recording: ${recording.cameras.length} frames.`;
}

function toggleRecording() {
  const button = $('record');
  if (recording.timer === null) {
    Object.assign(recording, { cameras: [], last: null, timer: setInterval(sampleFlight, 1000 / PATH_FPS) });
    sampleFlight();
    button.textContent = 'Stop recording';
    button.setAttribute('aria-pressed', 'true');
    $('download-path').disabled = true;
    return;
  }
  clearInterval(recording.timer);
  recording.timer = null;
  button.textContent = 'Record path';
  button.setAttribute('aria-pressed', 'false');
  const n = recording.cameras.length;
  $('download-path').disabled = n === 0;
  $('path-status').textContent = `Recorded ${n} frames (${(n / PATH_FPS).toFixed(1)} s at ${PATH_FPS} fps).`;
}

function downloadPath() {
  const path = nerfstudioPath(recording.cameras, state.scene.base, PATH_FPS);
  const blob = new Blob([JSON.stringify(path, null, 1)], { type: 'application/json' });
  const link = Object.assign(document.createElement('a'), { href: URL.createObjectURL(blob), download: 'camera_path.json' });
  link.click();
  setTimeout(() => URL.revokeObjectURL(link.href), 1000);
}

/** The models served (GET /v1/models): the picker lists them when there is a choice; the line says the chosen one. */
async function showModel() {
  try {
    const { body } = await api.models();
    const chosen = body.models.find((m) => m.name === api.modelName) ?? body.models.find((m) => m.default);
    // The default model is the server's: requests name none, as a page of one model sends them.
    api.modelName = chosen.default ? null : chosen.name;
    const options = body.models.map((m) => Object.assign(document.createElement('option'), { value: m.name, textContent: m.name, selected: m === chosen }));
    $('model-select').replaceChildren(...options);
    $('model-field').hidden = body.models.length < 2;
    $('model').textContent = `${chosen.model_id} (${chosen.variant})`;
  } catch (e) {
    // The reason is in the error box when it matters (the scene upload is refused alike).
    $('model').textContent = `Model unknown (${e.status ? `HTTP ${e.status}` : 'no answer'})`;
  }
}

/** Another model chosen: the scene is uploaded to it (a scene belongs to one model), then rendered again. */
async function modelChanged() {
  api.modelName = $('model-select').value;
  await showModel();
  const name = $('model-select').value;
  if (!state.scene) return openExample();
  progressive.stop();
  setStatus(`Uploading ${state.scene.label} to the model ${name}…`, 'uploading');
  try {
    state.scene.id = await state.scene.upload(api);
    clearError();
    setView(state.view);
  } catch (e) {
    showError(e);
    setStatus(`Could not upload ${state.scene.label} to the model ${name}.`, 'error');
  }
}

function saveView() {
  canvas.toBlob((blob) => {
    const link = Object.assign(document.createElement('a'), { href: URL.createObjectURL(blob), download: `scnerf-${state.mode}-${canvas.width}x${canvas.height}.png` });
    link.click();
    setTimeout(() => URL.revokeObjectURL(link.href), 1000);
  }, 'image/png');
}

function stop() {
  if (progressive.stop()) setStatus('Stopped. Move the camera to render again.', 'stopped');
}

/** With a new token: load what could not be loaded, or render again what was refused. */
function tokenChanged() {
  sessionStorage.setItem(TOKEN_KEY, $('token').value.trim());
  showModel();
  if (!state.scene) openExample();
  else setView(state.view);
}

function dropTarget() {
  const zone = $('dropzone');
  document.addEventListener('dragover', (e) => {
    if (!e.dataTransfer.types.includes('Files')) return;
    e.preventDefault();
    zone.hidden = false;
  });
  zone.addEventListener('dragleave', () => (zone.hidden = true));
  document.addEventListener('drop', async (e) => {
    e.preventDefault();
    zone.hidden = true;
    openCapture(await filesFromDrop(e.dataTransfer));
  });
}

function wire() {
  $('token').value = sessionStorage.getItem(TOKEN_KEY) ?? '';
  $('token').addEventListener('change', tokenChanged);
  $('model-select').addEventListener('change', modelChanged);
  $('open-capture').addEventListener('click', () => $('capture-input').click());
  $('capture-input').addEventListener('change', (e) => {
    openCapture(filesFromPicker(e.target.files));
    e.target.value = '';
  });
  for (const radio of document.querySelectorAll('input[name=mode]')) {
    radio.addEventListener('change', () => {
      state.mode = radio.value;
      redraw();
    });
  }
  for (const id of ['coarsest', 'finest']) $(id).addEventListener('change', () => state.view && setView(state.view));
  $('stop').addEventListener('click', stop);
  $('save').addEventListener('click', saveView);
  $('full-still').addEventListener('click', fullQualityStill);
  $('reset').addEventListener('click', reset);
  $('record').addEventListener('click', toggleRecording);
  $('download-path').addEventListener('click', downloadPath);
  window.addEventListener('resize', () => state.scene && drawOverview());
  drawColourBar($('colour-bar'));
  dropTarget();
  // The view is letterboxed (object-fit: contain): its pixels are scaled by the tighter side.
  const shown = () => Math.min(canvas.clientWidth / state.scene.base.width, canvas.clientHeight / state.scene.base.height);
  const lens = () => ({ up: state.geometry.up, radius: state.geometry.radius, focal: shown() * intrinsicsOf(state.scene.base).fx });
  const view = { get: () => state.view, set: setView };
  attachControls(canvas, view, lens, { snap, reset, stop });
}

wire();
// The example goes to the model chosen: the default, unless the list says otherwise first.
showModel().then(openExample);
