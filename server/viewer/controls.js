// Mouse, trackpad, touch and keyboard input on the view, turned into camera moves.
//
// Mouse: drag orbits, right- or Shift-drag pans, Alt- or Ctrl-drag rolls, middle-drag and the
// wheel dolly. Trackpad: two-finger scroll and pinch dolly. Touch: one finger orbits; two
// fingers pan (move), dolly (pinch) and roll (twist). Keys: see `KEYS`.

import { dolly, orbit, pan, roll } from './camera.js';

/** A drag across the whole view turns the camera half a turn (orbit and roll). */
const TURN_PER_WIDTH = Math.PI;
/** Wheel pixels to dolly: e^(delta * k). Pinches arrive as small ctrl-wheel deltas: amplified. */
const DOLLY_PER_PIXEL = 0.002;
const PINCH_GAIN = 5;
const KEY_ANGLE = Math.PI / 36;
const KEY_PAN = 0.05;
const KEY_DOLLY = 1.1;
/** The camera stops this fraction of the scene's radius short of its pivot. */
const MIN_DISTANCE = 0.01;

/** Which move a one-pointer drag makes, from its button and modifiers. */
function dragMode(e) {
  if (e.button === 2 || e.shiftKey) return 'pan';
  if (e.altKey || e.ctrlKey || e.metaKey) return 'roll';
  if (e.button === 1) return 'dolly';
  return 'orbit';
}

/** Wheel deltas in pixels, whatever unit the device reports. */
function wheelPixels(e) {
  return e.deltaY * [1, 16, 400][e.deltaMode];
}

/**
 * `view` is {get(), set(view)}; `lens()` is {up, radius, focal: the view's focal length in CSS
 * pixels}; `keys` maps actions (snap(i), reset, stop) to the page.
 */
export function attachControls(canvas, view, lens, keys) {
  const width = () => canvas.clientWidth || 1;
  const moves = {
    orbit: (v, dx, dy) => orbit(v, lens().up, (-dx / width()) * TURN_PER_WIDTH, (-dy / width()) * TURN_PER_WIDTH),
    pan: (v, dx, dy) => pan(v, -dx / lens().focal, -dy / lens().focal),
    roll: (v, dx) => roll(v, (dx / width()) * TURN_PER_WIDTH),
    dolly: (v, dx, dy) => dolly(v, Math.exp(dy * DOLLY_PER_PIXEL), MIN_DISTANCE * lens().radius),
  };
  const pointers = new Map();
  let mode = 'orbit';
  /** Applies a move to the current view (none before a scene is open). */
  const change = (move) => {
    const v = view.get();
    if (v) view.set(move(v));
  };

  canvas.addEventListener('contextmenu', (e) => e.preventDefault());
  canvas.addEventListener('pointerdown', (e) => {
    canvas.setPointerCapture(e.pointerId);
    pointers.set(e.pointerId, { x: e.clientX, y: e.clientY });
    mode = dragMode(e);
    canvas.focus();
    e.preventDefault();
  });
  canvas.addEventListener('pointermove', (e) => {
    const before = pointers.get(e.pointerId);
    if (!before) return;
    const others = [...pointers].filter(([id]) => id !== e.pointerId).map(([, p]) => p);
    const after = { x: e.clientX, y: e.clientY };
    pointers.set(e.pointerId, after);
    if (others.length === 0) change((v) => moves[mode](v, after.x - before.x, after.y - before.y));
    else if (others.length === 1) change((v) => twoFingers(v, others[0], before, after));
  });
  const release = (e) => pointers.delete(e.pointerId);
  canvas.addEventListener('pointerup', release);
  canvas.addEventListener('pointercancel', release);
  canvas.addEventListener(
    'wheel',
    (e) => {
      e.preventDefault();
      const gain = e.ctrlKey ? PINCH_GAIN : 1;
      change((v) => dolly(v, Math.exp(wheelPixels(e) * DOLLY_PER_PIXEL * gain), MIN_DISTANCE * lens().radius));
    },
    { passive: false },
  );

  /** One finger moved from `a` to `b` while the other stays at `still`. */
  function twoFingers(v, still, a, b) {
    const mid = (p) => ({ x: (p.x + still.x) / 2, y: (p.y + still.y) / 2 });
    const spread = (p) => Math.hypot(p.x - still.x, p.y - still.y) || 1;
    const angle = (p) => Math.atan2(p.y - still.y, p.x - still.x);
    const moved = moves.pan(v, mid(b).x - mid(a).x, mid(b).y - mid(a).y);
    const pinched = dolly(moved, spread(a) / spread(b), MIN_DISTANCE * lens().radius);
    return roll(pinched, -(angle(b) - angle(a)));
  }

  const KEYS = {
    ArrowLeft: (v, shift) => (shift ? pan(v, -KEY_PAN, 0) : orbit(v, lens().up, KEY_ANGLE, 0)),
    ArrowRight: (v, shift) => (shift ? pan(v, KEY_PAN, 0) : orbit(v, lens().up, -KEY_ANGLE, 0)),
    ArrowUp: (v, shift) => (shift ? pan(v, 0, -KEY_PAN) : orbit(v, lens().up, 0, KEY_ANGLE)),
    ArrowDown: (v, shift) => (shift ? pan(v, 0, KEY_PAN) : orbit(v, lens().up, 0, -KEY_ANGLE)),
    '+': (v) => dolly(v, 1 / KEY_DOLLY, MIN_DISTANCE * lens().radius),
    '=': (v) => dolly(v, 1 / KEY_DOLLY, MIN_DISTANCE * lens().radius),
    '-': (v) => dolly(v, KEY_DOLLY, MIN_DISTANCE * lens().radius),
    q: (v) => roll(v, -KEY_ANGLE),
    e: (v) => roll(v, KEY_ANGLE),
  };
  document.addEventListener('keydown', (e) => {
    // Typing in the token field or moving through a select is not steering the camera.
    if (e.target.closest('input, select, textarea') || e.metaKey || e.ctrlKey || e.altKey) return;
    const key = e.key.length === 1 ? e.key.toLowerCase() : e.key;
    if (KEYS[key]) change((v) => KEYS[key](v, e.shiftKey));
    else if (/^[1-9]$/.test(key)) keys.snap(Number(key) - 1);
    else if (key === '0' || key === 'Home') keys.reset();
    else if (key === 'Escape') keys.stop();
    else return;
    e.preventDefault();
  });
}
