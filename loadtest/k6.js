// k6 load test of scnerf-server's cached-scene endpoint, for users who have k6
// (https://k6.io). The bundled Rust load generator (loadtest/src/main.rs, loadtest/overload.sh)
// does the same without k6.
//
//   k6 run -e ADDR=127.0.0.1:8080 loadtest/k6.js                 # 2 VUs, 60 s, 64x64 views
//   k6 run -e ADDR=... -e VUS=8 -e DURATION=5m -e SIZE=64 -e TOKEN=... loadtest/k6.js
//   k6 run -e ADDR=... -e RATE=8 loadtest/k6.js                  # open loop: 8 requests/s
//
// setup() creates one scene from the parity fixture case (CASE, relative to this file); every
// iteration renders a SIZE x SIZE view of it. Only 200, 429 and 503 are acceptable answers
// (429/503 are load shedding); anything else fails the run.
import http from 'k6/http';
import { check } from 'k6';
import { Rate } from 'k6/metrics';

const ADDR = __ENV.ADDR || '127.0.0.1:8080';
const SIZE = parseInt(__ENV.SIZE || '64', 10);
const CASE = __ENV.CASE || '../tests/fixtures/parity/cases/opencv_64x96';
const TOKEN = __ENV.TOKEN || '';
const BASE = `http://${ADDR}`;

const request = JSON.parse(open(`${CASE}/request.json`));
const sources = [0, 1, 2].map((i) => open(`${CASE}/source_${i}.png`, 'b'));

const unexpected = new Rate('unexpected_status');
const shed = new Rate('shed');

export const options = __ENV.RATE
  ? {
      scenarios: {
        open: {
          executor: 'constant-arrival-rate',
          rate: parseFloat(__ENV.RATE),
          timeUnit: '1s',
          duration: __ENV.DURATION || '60s',
          preAllocatedVUs: 16,
          maxVUs: 64,
        },
      },
      thresholds: { unexpected_status: ['rate==0'] },
    }
  : {
      vus: parseInt(__ENV.VUS || '2', 10),
      duration: __ENV.DURATION || '60s',
      thresholds: { unexpected_status: ['rate==0'], http_req_failed: ['rate<0.01'] },
    };

function headers(extra) {
  const h = Object.assign({}, extra);
  if (TOKEN) h.Authorization = `Bearer ${TOKEN}`;
  return h;
}

// The target camera resized to SIZE x SIZE (pixel centres stay at integer coordinates).
function view() {
  const t = JSON.parse(JSON.stringify(request.target));
  const sx = SIZE / t.width;
  const sy = SIZE / t.height;
  const i = t.intrinsics;
  t.intrinsics = { fx: i.fx * sx, fy: i.fy * sy, cx: (i.cx + 0.5) * sx - 0.5, cy: (i.cy + 0.5) * sy - 0.5 };
  t.width = SIZE;
  t.height = SIZE;
  return JSON.stringify({ target: t, outputs: ['rgb'] });
}

export function setup() {
  const scene = Object.assign({}, request);
  delete scene.target;
  delete scene.outputs;
  const body = { request: JSON.stringify(scene) };
  sources.forEach((data, i) => {
    body[`source_${i}`] = http.file(data, `source_${i}.png`, 'image/png');
  });
  const res = http.post(`${BASE}/v1/scenes`, body, { headers: headers({}), timeout: '600s' });
  if (res.status !== 201) throw new Error(`POST /v1/scenes: ${res.status} ${res.body}`);
  return { path: `/v1/scenes/${res.json('scene_id')}/render`, body: view() };
}

export default function (data) {
  const res = http.post(`${BASE}${data.path}`, data.body, {
    headers: headers({ 'Content-Type': 'application/json', Accept: 'image/png' }),
    timeout: '600s',
    responseCallback: http.expectedStatuses(200),
  });
  const ok = [200, 429, 503].includes(res.status);
  unexpected.add(!ok);
  shed.add(res.status === 429 || res.status === 503);
  check(res, { 'status is 200/429/503': () => ok, 'PNG when 200': (r) => r.status !== 200 || r.headers['Content-Type'] === 'image/png' });
}
