// The viewer in headless Chromium against a running server (started by scripts/viewer-test.sh
// with a bearer token and debug logs of the executor in JSON). Fails (exit 1) on the first
// broken expectation; screenshots go to OUT.
//
// Env: VIEWER_URL (http://host:port/), SERVER_LOG (the server's JSON log), VIEWER_TOKEN,
// OUT (screenshots), CHROMIUM (browser binary).

import { mkdirSync, mkdtempSync, readFileSync, writeFileSync } from 'node:fs';
import { tmpdir } from 'node:os';
import { join } from 'node:path';
import { chromium } from 'playwright-core';

const { VIEWER_URL, SERVER_LOG, VIEWER_TOKEN, OUT } = process.env;
const CHROMIUM = process.env.CHROMIUM || '/usr/bin/chromium';
const origin = new URL(VIEWER_URL).origin;
const started = Date.now();
const sleep = (ms) => new Promise((r) => setTimeout(r, ms));
/** How long a step may wait for the server: an upper bound for a loaded 2-core machine, never a
 *  race (every wait ends at its event). */
const PATIENCE_MS = 300_000;

function log(message) {
  console.log(`[${((Date.now() - started) / 1000).toFixed(1).padStart(6)} s] ${message}`);
}

function check(condition, message) {
  if (!condition) throw new Error(`FAILED: ${message}`);
  log(`ok: ${message}`);
}

// ---- what the server did, from its log and /metrics ----

/** The server's JSON log lines of one request id (its span carries the id the page sent). */
function serverLines(requestId) {
  return readFileSync(SERVER_LOG, 'utf8')
    .split('\n')
    .filter((l) => l.includes(requestId))
    .map((l) => JSON.parse(l))
    .filter((l) => l.span?.request_id === requestId);
}

/** Renderer runs (one per chunk of rays, of any of the renderer graphs) the executor ran for a request. */
function rendererRuns(requestId) {
  return serverLines(requestId).filter((l) => l.fields.message === 'graph run' && l.fields.graph.startsWith('renderer')).length;
}

async function metric(name, labels = '') {
  const text = await (await fetch(`${origin}/metrics`)).text();
  const line = text.split('\n').find((l) => l.startsWith(labels ? `${name}{${labels}}` : `${name} `));
  return line ? Number(line.split(' ').pop()) : 0;
}

async function waitFor(what, predicate, timeoutMs = PATIENCE_MS) {
  const until = Date.now() + timeoutMs;
  for (;;) {
    const value = await predicate();
    if (value) return value;
    if (Date.now() > until) throw new Error(`FAILED: timed out waiting for ${what}`);
    await sleep(100);
  }
}

// ---- the page ----

const browser = await chromium.launch({ executablePath: CHROMIUM, args: ['--no-sandbox'] });
const context = await browser.newContext({ viewport: { width: 1280, height: 860 }, acceptDownloads: true, hasTouch: true });
const page = await context.newPage();
page.setDefaultTimeout(PATIENCE_MS);
const urls = [];
const pageErrors = [];
/** Render requests in order: {id, width, height, matrix, status ('pending', HTTP status, or the failure)}. */
const renders = [];
const renderOf = (request) => renders.find((r) => r.request === request);

page.on('pageerror', (e) => pageErrors.push(e.message));
page.on('console', (m) => m.type() === 'error' && pageErrors.push(m.text()));
page.on('request', (request) => {
  urls.push(request.url());
  if (!request.url().endsWith('/render')) return;
  const { target, sampling } = request.postDataJSON();
  const id = request.headers()['x-request-id'];
  renders.push({ request, id, width: target.width, height: target.height, matrix: target.pose.matrix, sampling, status: 'pending', at: Date.now() });
});
page.on('requestfinished', async (request) => {
  const render = renderOf(request);
  if (render) render.status = (await request.response()).status();
});
page.on('requestfailed', (request) => {
  const render = renderOf(request);
  if (render) render.status = request.failure().errorText;
});

const frames = () => page.$eval('#view', (c) => Number(c.dataset.frames));
const phase = () => page.$eval('#view', (c) => c.dataset.state);
/** The view canvas scaled to 64x48, as RGBA bytes: comparable whatever size was rendered. */
const pixels = () =>
  page.$eval('#view', (c) => {
    const small = Object.assign(document.createElement('canvas'), { width: 64, height: 48 });
    const ctx = small.getContext('2d');
    ctx.drawImage(c, 0, 0, 64, 48);
    return Array.from(ctx.getImageData(0, 0, 64, 48).data);
  });
/** The first render requested from index `from` on that the server answered. */
const firstAnswered = (from) => waitFor('an answered render', () => renders.slice(from).find((r) => r.status === 200));
const meanDifference = (a, b) => a.reduce((s, v, i) => s + Math.abs(v - b[i]), 0) / a.length;
const sameMatrix = (a, b) => a.every((row, i) => row.every((v, j) => Math.abs(v - b[i][j]) < 1e-6));
const shot = (name) => page.screenshot({ path: join(OUT, name) });

async function viewCentre() {
  // A click on a button below the view may have scrolled it partly out of the window.
  await page.locator('#view').scrollIntoViewIfNeeded();
  const box = await page.locator('#view').boundingBox();
  return [box.x + box.width / 2, box.y + box.height / 2];
}

async function drag(dx, dy) {
  const [x, y] = await viewCentre();
  await page.mouse.move(x, y);
  await page.mouse.down();
  await page.mouse.move(x + dx, y + dy, { steps: 12 });
  await page.mouse.up();
}

/** The example the page opens on, as the server serves it. */
const exampleFile = async (name) => Buffer.from(await (await fetch(`${origin}/viewer/example/${name}`)).arrayBuffer());
const example = JSON.parse(await exampleFile('request.json'));
const size = (fraction) => [Math.round(example.target.width * fraction), Math.round(example.target.height * fraction)];

try {
  log(`opening ${VIEWER_URL}`);
  await page.goto(VIEWER_URL);

  // 0. The camera maths, in the page's own module: conventions, scaling, orbits.
  const maths = await page.evaluate(async () => {
    const c = await import('/viewer/camera.js');
    const gap = (p, q) => Math.hypot(p[0] - q[0], p[1] - q[1], p[2] - q[2]);
    const matrix = [[0, -1, 0, 1], [0, 0, -1, 2], [1, 0, 0, 3], [0, 0, 0, 1]];
    const camera = { width: 8, height: 6, intrinsics: { fx: 10, fy: 10, cx: 3.5, cy: 2.5 }, pose: { matrix, kind: 'world_to_camera', axes: 'opencv' } };
    const pose = c.poseOf(camera);
    // The same camera as OpenGL camera-to-world (y and z flipped) reads back as the same pose.
    const gl = c.cameraAt(camera, pose, 1).pose.matrix.map((row) => [row[0], -row[1], -row[2], row[3]]);
    const again = c.poseOf({ ...camera, pose: { matrix: gl, kind: 'camera_to_world', axes: 'opengl' } });
    const view = c.viewFrom(pose, { centre: [0, 0, 0], up: [0, 0, 1], radius: 3 });
    const turned = c.orbit(view, [0, 0, 1], 0.7, 0.3);
    return {
      centre: pose.centre,
      conventions: gap(pose.centre, again.centre) + gap(pose.forward, again.forward) + gap(pose.right, again.right),
      half: c.cameraAt(camera, pose, 0.5).intrinsics,
      pivot: view.pivot,
      orbit: [gap(view.pose.centre, view.pivot), gap(turned.pose.centre, turned.pivot), gap(view.pivot, turned.pivot)],
      aim: gap(c.normalize(c.sub(turned.pivot, turned.pose.centre)), turned.pose.forward),
    };
  });
  check(maths.centre.join() === '-3,1,2' && maths.conventions < 1e-12, 'world-to-camera and OpenGL camera-to-world read as one pose');
  check(JSON.stringify(maths.half) === '{"fx":5,"fy":5,"cx":1.5,"cy":1}', 'half size halves the focal length about pixel centres');
  check(maths.pivot.join() === '0,1,2', 'the view orbits the point of its axis nearest the scene centre');
  const [r0, r1, moved0] = maths.orbit;
  check(Math.abs(r0 - r1) < 1e-9 && moved0 < 1e-9 && maths.aim < 1e-9, 'an orbit keeps the distance, the pivot and the aim');

  // 1. The server wants a token: the page says so in the server's own words.
  await page.locator('#error').filter({ hasText: 'missing bearer token' }).waitFor();
  const tokenError = await page.textContent('#error');
  check(/API token/.test(tokenError) && /HTTP 401/.test(tokenError), `a refused upload shows the server's message: "${tokenError}"`);
  await shot('01-token-needed.png');

  // 2. With the token, the example appears, coarse first, then finer sizes replace it.
  const typed = Date.now();
  await page.fill('#token', VIEWER_TOKEN);
  await page.press('#token', 'Tab');
  await page.waitForFunction(() => Number(document.querySelector('#view').dataset.frames) >= 1);
  log(`first render ${((Date.now() - typed) / 1000).toFixed(1)} s after the token (scene upload + coarse view)`);
  await waitFor('the first progressive chain', async () => (await phase()) === 'idle');
  const firstChain = renders.filter((r) => r.status === 200).map((r) => [r.width, r.height]);
  const expected = [1 / 8, 1 / 4, 1 / 2].map(size);
  check(JSON.stringify(firstChain) === JSON.stringify(expected), `sizes arrived coarse to fine: ${JSON.stringify(firstChain)}`);
  check(sameMatrix(renders[0].matrix, cameraToWorld(example.target)), 'the page opens at the example\'s target view');
  check((await frames()) === 3, 'each size was drawn');
  const finest = renders[2];
  const runsPerFinest = rendererRuns(finest.id);
  check(runsPerFinest > 1, `the finest size took ${runsPerFinest} renderer runs (chunks)`);
  check(renders.slice(0, 3).every((r) => r.sampling === undefined), 'while moving, views take the server\'s default sampling');
  check(/guided, [\d.]+ network samples per pixel/.test(await page.textContent('#info')), 'the page says the view was guided');
  await shot('02-example.png');

  // 2b. The full-quality still: the finest size again, every ray sampled in full.
  const stillFrom = renders.length;
  await page.click('#full-still');
  const still = await firstAnswered(stillFrom);
  check(still.sampling === 'full' && still.width === expected[2][0], `the still asked for full sampling at ${still.width}x${still.height}`);
  await waitFor('the still to be shown', async () => (await phase()) === 'idle');
  check(/full, 32\.0 network samples per pixel/.test(await page.textContent('#info')), 'the page says the still was sampled in full');
  check(/in full quality/.test(await page.textContent('#status')), 'the status names the full-quality still');
  const before = await pixels();

  // 3. Depth and opacity, then back to RGB; the view saves as PNG.
  await page.check('input[value=depth]');
  const depth = await pixels();
  await shot('03-depth.png');
  await page.check('input[value=opacity]');
  const opacity = await pixels();
  await shot('04-opacity.png');
  await page.check('input[value=rgb]');
  check(meanDifference(before, depth) > 5 && meanDifference(depth, opacity) > 5, 'depth and opacity draw differently from RGB');
  check(meanDifference(before, await pixels()) === 0, 'RGB again is the same picture');
  const [download] = await Promise.all([page.waitForEvent('download'), page.click('#save')]);
  const png = readFileSync(await download.path());
  check(png.subarray(1, 4).toString() === 'PNG' && png.readUInt32BE(16) === expected[2][0], `saved ${download.suggestedFilename()}`);

  // 4. A drag with real mouse events renders a new pose.
  const count = renders.length;
  await drag(160, 40);
  const moved = await firstAnswered(count);
  check(!sameMatrix(moved.matrix, renders[0].matrix), `a render of a new pose arrived (${moved.width}x${moved.height})`);

  // 5. Dragging while a view is rendering aborts it, and the server drops its remaining work. The
  //    request aborted is the full-quality still at the full size: every ray at all samples, many
  //    renderer runs, so it cannot finish between its first run and the drag, however fast the
  //    machine (a guided view at the finest size often did). The same still, left to finish,
  //    counts the runs a whole one takes.
  await chooseFinest(1);
  const [fullWidth] = size(1);
  const stillAtFull = async (from) => {
    await page.click('#full-still');
    return waitFor('the full-size still to be asked for', () => renders.slice(from).find((r) => r.sampling === 'full' && r.width === fullWidth));
  };
  const inFlight = await stillAtFull(renders.length);
  await waitFor(`${inFlight.id}'s first renderer run`, () => rendererRuns(inFlight.id) >= 1 || inFlight.status !== 'pending');
  check(inFlight.status === 'pending', `${inFlight.id} is rendering (${rendererRuns(inFlight.id)} runs so far)`);
  const dragged = Date.now();
  const next = renders.length;
  await drag(-120, 60);
  await waitFor('the aborted request to fail in the browser', () => inFlight.status !== 'pending', 10_000);
  check(inFlight.status === 'net::ERR_ABORTED', `the browser aborted ${inFlight.id} (${inFlight.status})`);
  const atAbort = rendererRuns(inFlight.id);
  const second = await firstAnswered(next);
  log(`the new pose's first size arrived ${((Date.now() - dragged) / 1000).toFixed(1)} s after the drag`);
  check(!sameMatrix(second.matrix, moved.matrix), 'the second drag rendered its own pose');
  await waitFor('the chain after the drags', async () => (await phase()) === 'idle');
  const whole = await stillAtFull(renders.length);
  await waitFor(`${whole.id} to be answered`, () => whole.status !== 'pending');
  check(whole.status === 200, `a whole full-size still took ${rendererRuns(whole.id)} renderer runs`);
  const later = rendererRuns(inFlight.id);
  check(later <= atAbort + 1, `no renderer runs for ${inFlight.id} after the abort but the one running (${atAbort} -> ${later})`);
  check(later < rendererRuns(whole.id), `${inFlight.id} ran ${later} of a still's ${rendererRuns(whole.id)} runs: the server dropped the rest`);
  check(!serverLines(inFlight.id).some((l) => l.fields.message === 'rendered'), `the server never finished ${inFlight.id}`);
  await chooseFinest(0.5);
  const after = await pixels();
  check(meanDifference(before, after) > 2, `the canvas changed (mean difference ${meanDifference(before, after).toFixed(1)} of 255)`);
  await shot('05-after-drag.png');

  // 6. Keyboard: 2 snaps to the second captured view; Escape stops rendering.
  const keyed = renders.length;
  await page.locator('#view').focus();
  await page.keyboard.press('2');
  await waitFor('a render after the key', () => renders.length > keyed);
  check(sameMatrix(renders[keyed].matrix, cameraToWorld(example.sources[1].camera)), 'key 2 views from captured camera 2');
  const snapped = renders[keyed];

  // 7. Wheel (a trackpad's two-finger scroll), a two-finger pinch and a one-finger touch drag.
  const cdp = await context.newCDPSession(page);
  const touch = (type, points) => cdp.send('Input.dispatchTouchEvent', { type, touchPoints: points.map(([x, y], id) => ({ x, y, id })) });
  const [x, y] = await viewCentre();
  await page.mouse.move(x, y);
  const wheeled = await gesture(() => page.mouse.wheel(0, -200));
  check(dollied(snapped.matrix, wheeled.matrix), 'the wheel moves the camera forward along its axis');
  const pinched = await gesture(async () => {
    const apart = (d) => [[x - d, y], [x + d, y]];
    await touch('touchStart', apart(40));
    for (let i = 1; i <= 8; i++) await touch('touchMove', apart(40 + 10 * i));
    await touch('touchEnd', []);
  });
  check(dollied(wheeled.matrix, pinched.matrix), 'spreading two fingers moves the camera forward');
  const swiped = await gesture(async () => {
    await touch('touchStart', [[x, y]]);
    for (let i = 1; i <= 8; i++) await touch('touchMove', [[x + 15 * i, y]]);
    await touch('touchEnd', []);
  });
  check(!sameMatrix(rotation(swiped.matrix), rotation(pinched.matrix)), 'a one-finger swipe turns the camera');

  // 7b. A recorded flight downloads as nerfstudio's camera_path.json, starting where the camera was.
  const startMatrix = renders[renders.length - 1].matrix;
  await page.click('#record');
  await drag(100, 20);
  await sleep(400);
  await page.click('#record');
  const [pathDownload] = await Promise.all([page.waitForEvent('download'), page.click('#download-path')]);
  const flight = JSON.parse(readFileSync(await pathDownload.path(), 'utf8'));
  const base = example.target;
  check(pathDownload.suggestedFilename() === 'camera_path.json' && flight.camera_type === 'perspective', 'the recorded path downloads as camera_path.json');
  check(flight.render_width === base.width && flight.render_height === base.height && flight.fps === 24, `render size ${flight.render_width}x${flight.render_height} at ${flight.fps} fps`);
  check(flight.camera_path.length >= 2 && Math.abs(flight.seconds - flight.camera_path.length / 24) < 1e-9, `${flight.camera_path.length} frames, ${flight.seconds.toFixed(2)} s`);
  const fov = (2 * Math.atan(base.height / 2 / base.intrinsics.fy) * 180) / Math.PI;
  check(flight.camera_path.every((c) => c.camera_to_world.length === 16 && Math.abs(c.fov - fov) < 1e-9 && Math.abs(c.aspect - base.width / base.height) < 1e-12), `every frame: 16 numbers, fov ${fov.toFixed(3)} degrees, aspect`);
  // OpenGL camera-to-world back to the page's OpenCV one: flip the y and z columns
  const opencv = (flat) => [0, 1, 2, 3].map((r) => flat.slice(4 * r, 4 * r + 4).map((v, c) => (r < 3 && (c === 1 || c === 2) ? -v : v)));
  check(sameMatrix(opencv(flight.camera_path[0].camera_to_world), startMatrix), 'the path starts at the pose shown when recording began');
  check(!sameMatrix(opencv(flight.camera_path.at(-1).camera_to_world), startMatrix), 'and follows the drag');

  // A move starts a render chain; Escape at once stops it (on an idle view Escape has nothing to stop).
  await drag(30, 0);
  await page.keyboard.press('Escape');
  await waitFor('the stop', async () => (await phase()) === 'stopped', 10_000);
  check(true, 'Escape stopped rendering');

  // 8. A capture folder: a broken one is refused in the server's words and the example stays; a
  //    nerfstudio capture of the example's three photos opens as a scene of its own and renders.
  const broken = await captureFolder('{"frames": []}', ['source_0.png']);
  await page.setInputFiles('#capture-input', broken);
  const refused = await page.locator('#error').filter({ hasText: 'HTTP 422' }).textContent();
  check(/transforms\.json/.test(refused), `a broken capture shows the server's message: "${refused.trim()}"`);
  check(/Still showing the example/.test(await page.textContent('#status')), 'a refused capture keeps the example on screen');
  await shot('06-capture-refused.png');

  const exampleScene = renders[0].request.url();
  const dropped = renders.length;
  // With a second image set (images_2/) beside images/, a Finder file and a hidden image: the page
  // reads the server's limits, asks the server's plan (the listing, then one image's size a
  // folder) and sends what it says: one set, the largest that fits (here images/), nothing hidden.
  const folder = await captureFolder(nerfstudio(example), ['source_0.png', 'source_1.png', 'source_2.png']);
  mkdirSync(join(folder, 'images_2'));
  for (const i of [1, 2, 3]) writeFileSync(join(folder, 'images_2', `photo_${i}.png`), readFileSync(join(folder, 'images', `photo_${i}.png`)));
  writeFileSync(join(folder, '.DS_Store'), 'Bud1');
  writeFileSync(join(folder, 'images', '._photo_1.png'), 'AppleDouble');
  // The files of the upload, as the page hands them to fetch (the browser does not report a
  // multipart body of files).
  await page.evaluate(() => {
    const fetched = window.fetch;
    window.fetch = (url, init) => {
      if (String(url).endsWith('/v1/captures') && init?.body instanceof FormData) window.sentFiles = init.body.getAll('file').map((f) => f.name);
      return fetched(url, init);
    };
  });
  const limitsRead = urls.length;
  const planned = [];
  const planning = (r) => r.url().endsWith('/v1/captures/plan') && planned.push(r) && false;
  const [uploaded] = await Promise.all([
    page.waitForResponse((r) => planning(r) || r.url().endsWith('/v1/captures')),
    page.setInputFiles('#capture-input', folder),
  ]);
  const answer = await uploaded.json();
  const asked = urls.slice(limitsRead);
  const at = (path) => asked.findIndex((u) => u.endsWith(path));
  check(at('/v1/limits') >= 0 && at('/v1/limits') < at('/v1/captures/plan') && at('/v1/captures/plan') < at('/v1/captures'), 'the page read GET /v1/limits and the plan before uploading');
  const listings = planned.map((r) => r.request().postDataJSON());
  check(listings.length === 2 && listings[0].files.includes('.DS_Store') && listings[1].sizes.map((s) => s.path).sort().join() === 'images/photo_1.png,images_2/photo_1.png', `the page listed every file, then gave the sizes asked for (${JSON.stringify(listings.map((l) => l.sizes ?? []))})`);
  const sent = (await page.evaluate(() => window.sentFiles)).sort();
  check(sent.join() === 'images/photo_1.png,images/photo_2.png,images/photo_3.png,transforms.json', `the page sent the files the plan named (${sent.join(', ')})`);
  // the server names any set it got but did not read: none, so only images/ was sent
  check(answer.image_set === 'images' && !answer.warnings.some((w) => w.includes('not read')), `only the image set that fits was sent (${answer.image_set}; ${JSON.stringify(answer.warnings)})`);
  const captured = await firstAnswered(dropped);
  check(captured.request.url() !== exampleScene, `the capture rendered as a scene of its own (${new URL(captured.request.url()).pathname})`);
  const info = await waitFor('the capture\'s first view in the panel', async () => {
    const text = await page.textContent('#info');
    return /photo_/.test(text) && text;
  });
  check(/photo_1/.test(info) && /photo_2/.test(info) && /photo_3/.test(info), `the page names the sources the server picked: "${info.match(/views [^R]*/)?.[0]}"`);
  check((await page.locator('#views button').count()) === 3, 'the capture\'s three cameras can be snapped to');
  await shot('07-capture.png');
  await page.keyboard.press('Escape');

  // 8b. Two models served (viewer-test.sh adds a copy of the bundle, "second"): the picker lists
  //     them; choosing the other uploads the scene to it, and its views come from it.
  const models = await page.$$eval('#model-select option', (os) => os.map((o) => o.value));
  check((await page.isVisible('#model-select')) && models.join() === 'bundle,second', `the model picker lists the models served (${models.join(', ')})`);
  const beforeSwitch = renders.length;
  const [reuploaded] = await Promise.all([
    page.waitForResponse((r) => r.url().endsWith('/v1/captures?model=second')),
    page.selectOption('#model-select', 'second'),
  ]);
  check(reuploaded.ok() && (await reuploaded.json()).model === 'second', 'choosing a model uploads the scene to it');
  const byOther = await firstAnswered(beforeSwitch);
  const answeredBy = (await byOther.request.response()).headers()['x-scnerf-model'];
  check(answeredBy === 'second', `the scene's views come from the model chosen (${answeredBy})`);
  await shot('08-model-chosen.png');
  await page.keyboard.press('Escape');

  // 9. The server's books: nothing left queued, and only the renders the page received were finished.
  await waitFor('an idle executor', async () => (await metric('scnerf_inference_queue_requests')) === 0);
  check((await metric('scnerf_inference_queue_jobs')) === 0, 'no graph runs left in the queue');
  const received = renders.filter((r) => r.status === 200).length;
  const aborted = renders.filter((r) => r.status === 'net::ERR_ABORTED');
  // An abort can cross a response already on its way: such a request was finished all the same.
  const crossed = aborted.filter((r) => serverLines(r.id).some((l) => l.fields.message === 'rendered')).length;
  const finished = await metric('scnerf_http_requests_total', 'route="/v1/scenes/{id}/render",method="POST",status="200"');
  check(finished === received + crossed, `the server finished the ${received} renders the page received and no other (${finished}, ${crossed} crossed an abort)`);
  log(`${renders.length} render requests: ${received} answered, ${aborted.length} aborted by the page`);

  // 10. Nothing came from anywhere but the server, and the page raised no error.
  const outside = urls.filter((u) => !u.startsWith(`${origin}/`) && !u.startsWith('data:') && !u.startsWith('blob:'));
  check(outside.length === 0, `all ${urls.length} requests went to ${origin} ${outside.join(' ')}`);
  check(pageErrors.every((e) => /status of (401|422)/.test(e)), `no script errors (${pageErrors.length} logged HTTP refusals, expected ones)`);

  writeFileSync(join(OUT, 'urls.txt'), `${urls.join('\n')}\n`);
  log('PASSED');
} catch (e) {
  console.error(e.message);
  await shot('failure.png').catch(() => {});
  process.exitCode = 1;
} finally {
  await browser.close();
}

/** Chooses the finest size, which renders the view again up to it: returns once that chain has
 *  asked for the finest size and been drawn (the page shows 'idle' before the chain starts, so
 *  waiting for 'idle' alone would race it). */
async function chooseFinest(fraction) {
  const from = renders.length;
  await page.selectOption('#finest', String(fraction));
  const [width] = size(fraction);
  await waitFor(`a render at the finest size ${width}`, () => renders.slice(from).some((r) => r.width === width));
  await waitFor('the chain up to the finest size', async () => (await phase()) === 'idle');
}

/** The request the page sends after `act` (the last one, once the gesture's events settled). */
async function gesture(act) {
  const from = renders.length;
  await act();
  await waitFor('a render request after the gesture', () => renders.length > from);
  await sleep(300);
  return renders[renders.length - 1];
}

/** A capture folder in a fresh temporary directory: `transforms` as transforms.json, and the
 *  example's `photos` as images/photo_1.png, photo_2.png, ... */
async function captureFolder(transforms, photos) {
  const folder = join(mkdtempSync(join(tmpdir(), 'viewer-test-')), 'capture');
  mkdirSync(join(folder, 'images'), { recursive: true });
  writeFileSync(join(folder, 'transforms.json'), transforms);
  for (const [i, name] of photos.entries()) writeFileSync(join(folder, 'images', `photo_${i + 1}.png`), await exampleFile(name));
  return folder;
}

/** The example's sources as a nerfstudio transforms.json: OpenGL camera-to-world, pixel centres
 *  at +0.5 (nerfstudio's convention), the example's depth range. */
function nerfstudio(request) {
  const { intrinsics, width, height } = request.sources[0].camera;
  const frames = request.sources.map(({ camera }, i) => ({
    file_path: `images/photo_${i + 1}.png`,
    transform_matrix: cameraToWorld(camera).map((row) => [row[0], -row[1], -row[2], row[3]]),
  }));
  const { fx, fy, cx, cy } = intrinsics;
  return JSON.stringify({ fl_x: fx, fl_y: fy, cx: cx + 0.5, cy: cy + 0.5, w: width, h: height, near: request.near, far: request.far, frames });
}

function rotation(m) {
  return m.slice(0, 3).map((row) => row.slice(0, 3));
}

/** `after` is `before` moved forward along its optical axis (no turn, next to no sideways move). */
function dollied(before, after) {
  const move = [0, 1, 2].map((i) => after[i][3] - before[i][3]);
  const forward = [0, 1, 2].map((i) => before[i][2]);
  const ahead = move.reduce((s, v, i) => s + v * forward[i], 0);
  const sideways = Math.hypot(...move.map((v, i) => v - ahead * forward[i]));
  return sameMatrix(rotation(before), rotation(after)) && ahead > 0 && sideways < 0.02 * ahead;
}

/** Camera-to-world (OpenCV) of an example camera, as the page sends it. */
function cameraToWorld(camera) {
  const m = camera.pose.matrix;
  if (camera.pose.kind === 'camera_to_world') return m;
  const r = [0, 1, 2].map((i) => [0, 1, 2].map((j) => m[j][i]));
  const t = [0, 1, 2].map((i) => -(r[i][0] * m[0][3] + r[i][1] * m[1][3] + r[i][2] * m[2][3]));
  return [[...r[0], t[0]], [...r[1], t[1]], [...r[2], t[2]], [0, 0, 0, 1]];
}
