// The server's HTTP API, as the page uses it. Every failure becomes an ApiError whose message
// says what went wrong in plain words, from the server's own error body where there is one.

/** A refused or failed call. `retryAfter` (seconds) is set when the server asked to retry. */
export class ApiError extends Error {
  constructor(message, { status = 0, code = '', retryAfter = null } = {}) {
    super(message);
    this.name = 'ApiError';
    this.status = status;
    this.code = code;
    this.retryAfter = retryAfter;
  }
}

/** What to add to the server's message so that the user knows what to do. */
function hint(status, code) {
  if (status === 401) return ' Enter the server\'s token in the "API token" field.';
  if (code === 'scene_not_found') return ' The scene will be uploaded again.';
  return '';
}

/** The ApiError of a non-2xx response: `{"error": {"code", "message", "field"}}` when it is ours. */
async function errorOf(response, what) {
  const text = await response.text().catch(() => '');
  let detail = null;
  try {
    detail = JSON.parse(text).error;
  } catch {
    // Not our JSON (a proxy's page, say): its text is still the best explanation there is.
  }
  const code = detail?.code ?? '';
  const message = detail?.message ?? (text.trim().slice(0, 300) || response.statusText || 'no explanation given');
  const field = detail?.field ? ` (field: ${detail.field})` : '';
  const seconds = Number.parseInt(response.headers.get('retry-after') ?? '', 10);
  const requestId = response.headers.get('x-request-id');
  const id = requestId ? `, request ${requestId}` : '';
  return new ApiError(
    `${what} failed: ${message}${field} [HTTP ${response.status}${code ? ` ${code}` : ''}${id}].${hint(response.status, code)}`,
    { status: response.status, code, retryAfter: Number.isFinite(seconds) ? seconds : null },
  );
}

export class Api {
  /** `token()` returns the bearer token to send, or '' for none. */
  constructor(token) {
    this.token = token;
    /** The model scenes are uploaded to (a name GET /v1/models lists), or null for the server's default. */
    this.modelName = null;
  }

  headers(extra = {}) {
    const token = this.token();
    return token ? { ...extra, Authorization: `Bearer ${token}` } : extra;
  }

  /**
   * fetch, with the server's refusals and network failures as ApiErrors. Aborts stay
   * AbortErrors: the caller cancelled on purpose and says nothing.
   */
  async send(what, url, init = {}) {
    let response;
    try {
      response = await fetch(url, { ...init, headers: this.headers(init.headers) });
    } catch (e) {
      if (e.name === 'AbortError') throw e;
      throw new ApiError(`${what} failed: the server at ${location.origin} did not answer (${e.message}). Is it still running?`);
    }
    if (!response.ok) throw await errorOf(response, what);
    return response;
  }

  async json(what, url, init) {
    const response = await this.send(what, url, init);
    try {
      return { body: await response.json(), headers: response.headers };
    } catch (e) {
      if (e.name === 'AbortError') throw e;
      throw new ApiError(`${what} failed: the server's answer is not the JSON expected (${e.message}).`);
    }
  }

  async blob(what, url) {
    return (await this.send(what, url)).blob();
  }

  model() {
    return this.json('Reading the model (GET /v1/model)', '/v1/model');
  }

  /** Every model the server serves, the default marked: `{models: [{name, model_id, variant, default, ...}], default}`. */
  models() {
    return this.json('Reading the models (GET /v1/models)', '/v1/models');
  }

  /** What the server accepts (source pixels, scene views, body sizes), read before any upload. */
  limits() {
    return this.json('Reading the server\'s limits (GET /v1/limits)', '/v1/limits');
  }

  /** `form`: multipart with `request` and `source_0..N`. */
  createScene(form, signal) {
    return this.json('Uploading the scene (POST /v1/scenes)', '/v1/scenes', { method: 'POST', body: form, signal });
  }

  /** What to send of a capture folder, from its `listing` ({files, sizes?}; see capture.js). */
  planCapture(listing) {
    return this.json('Planning the capture\'s upload (POST /v1/captures/plan)', '/v1/captures/plan', {
      method: 'POST',
      headers: { 'Content-Type': 'application/json' },
      body: JSON.stringify(listing),
    });
  }

  /** `form`: the capture's files, named by their paths (see capture.js); the scene belongs to the chosen model. */
  createCaptureScene(form, signal) {
    const url = this.modelName ? `/v1/captures?model=${encodeURIComponent(this.modelName)}` : '/v1/captures';
    return this.json('Uploading the capture (POST /v1/captures)', url, { method: 'POST', body: form, signal });
  }

  /**
   * A view of a cached scene, as JSON with rgb, depth and opacity; `sampling` (full, guided) or null for the server's default.
   * The scene's own model renders it (it was uploaded to the chosen one).
   */
  render(sceneId, target, requestId, signal, sampling = null) {
    const body = { target, outputs: ['rgb', 'depth', 'opacity'], ...(sampling ? { sampling } : {}) };
    return this.json(`Rendering ${target.width}x${target.height} (POST /v1/scenes/{id}/render)`, `/v1/scenes/${sceneId}/render`, {
      method: 'POST',
      signal,
      headers: { 'Content-Type': 'application/json', Accept: 'application/json', 'X-Request-Id': requestId },
      body: JSON.stringify(body),
    });
  }
}
