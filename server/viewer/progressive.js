// Progressive rendering: after a camera change the view is rendered coarse to fine, each size
// replacing the last on screen. The next change aborts whatever is outstanding (the fetch's
// AbortController closes the connection; the server then drops the aborted request's queued
// work), so the server only ever works on the view the user is looking at.

/**
 * Quiet time after a change before asking the server. A drag moves the camera on every pointer
 * event; without the pause each would start a request only for the next to abort it.
 */
const SETTLE_MS = 60;
/** Busy answers (429/503 with Retry-After) retried per size before the error is shown. */
const MAX_RETRIES = 5;

/** Resolves after `ms`, or rejects with an AbortError when `signal` aborts first. */
function sleep(ms, signal) {
  return new Promise((resolve, reject) => {
    const aborted = () => {
      clearTimeout(timer);
      reject(new DOMException('aborted', 'AbortError'));
    };
    const timer = setTimeout(() => {
      signal.removeEventListener('abort', aborted);
      resolve();
    }, ms);
    signal.addEventListener('abort', aborted, { once: true });
  });
}

export class Progressive {
  /**
   * `renderLevel(view, step, signal)` renders one step (a size, and how to sample it); `on` has
   * onStart(step), onFrame(frame, step), onDone(), onBusy(error, seconds), onError(error).
   */
  constructor(renderLevel, on) {
    this.renderLevel = renderLevel;
    this.on = on;
    this.controller = null;
    this.timer = null;
  }

  /** Cancels what is outstanding and renders `view` at `steps` (coarse first). */
  restart(view, steps) {
    this.stop();
    this.timer = setTimeout(() => {
      this.timer = null;
      this.run(view, steps);
    }, SETTLE_MS);
  }

  /** Cancels what is outstanding; true if there was something. */
  stop() {
    const pending = this.timer !== null || this.controller !== null;
    clearTimeout(this.timer);
    this.timer = null;
    this.controller?.abort();
    this.controller = null;
    return pending;
  }

  async run(view, steps) {
    const controller = new AbortController();
    this.controller = controller;
    try {
      for (const step of steps) {
        this.on.onStart(step);
        const frame = await this.withRetries(view, step, controller.signal);
        if (controller.signal.aborted) return;
        this.on.onFrame(frame, step);
      }
      this.on.onDone();
    } catch (e) {
      if (e.name !== 'AbortError') this.on.onError(e);
    } finally {
      if (this.controller === controller) this.controller = null;
    }
  }

  async withRetries(view, step, signal) {
    for (let attempt = 0; ; attempt++) {
      try {
        return await this.renderLevel(view, step, signal);
      } catch (e) {
        if (e.retryAfter == null || attempt >= MAX_RETRIES) throw e;
        this.on.onBusy(e, e.retryAfter);
        await sleep(e.retryAfter * 1000, signal);
      }
    }
  }
}
