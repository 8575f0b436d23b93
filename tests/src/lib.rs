//! Helpers for the end-to-end tests: a minimal blocking HTTP/1.1 client (no extra dependencies;
//! the load generator, `loadtest/`, uses it too), multipart encoding (the one builder of the workspace's
//! tests: the server's own tests use it too), test cases on disk, locating and starting the
//! server binary.

use std::io::{BufRead, BufReader, Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use serde_json::{json, Value};

/// Repository root (this crate lives in `<repo>/tests`).
pub fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).parent().expect("repo root").to_path_buf()
}

#[derive(Debug)]
pub struct HttpResponse {
    pub status: u16,
    pub headers: Vec<(String, String)>,
    pub body: Vec<u8>,
}

impl HttpResponse {
    pub fn header(&self, name: &str) -> Option<&str> {
        self.headers.iter().find(|(k, _)| k.eq_ignore_ascii_case(name)).map(|(_, v)| v.as_str())
    }
}

/// Sends one request on a fresh connection (`Connection: close`) and reads the whole response.
pub fn http_request(
    addr: SocketAddr,
    method: &str,
    path: &str,
    headers: &[(&str, &str)],
    body: &[u8],
    timeout: Duration,
) -> std::io::Result<HttpResponse> {
    let mut stream = TcpStream::connect_timeout(&addr, Duration::from_secs(10))?;
    stream.set_read_timeout(Some(timeout))?;
    stream.set_write_timeout(Some(timeout))?;
    let mut head =
        format!("{method} {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\nContent-Length: {}\r\n", body.len());
    for (k, v) in headers {
        head.push_str(&format!("{k}: {v}\r\n"));
    }
    head.push_str("\r\n");
    stream.write_all(head.as_bytes())?;
    stream.write_all(body)?;
    let mut reader = BufReader::new(stream);
    let mut status_line = String::new();
    reader.read_line(&mut status_line)?;
    let status = status_line
        .split_whitespace()
        .nth(1)
        .and_then(|s| s.parse().ok())
        .ok_or_else(|| std::io::Error::other(format!("bad status line {status_line:?}")))?;
    let mut headers = Vec::new();
    loop {
        let mut line = String::new();
        reader.read_line(&mut line)?;
        let line = line.trim_end();
        if line.is_empty() {
            break;
        }
        if let Some((k, v)) = line.split_once(':') {
            headers.push((k.trim().to_string(), v.trim().to_string()));
        }
    }
    let mut body = Vec::new();
    let chunked = headers.iter().any(|(k, v)| k.eq_ignore_ascii_case("transfer-encoding") && v.contains("chunked"));
    reader.read_to_end(&mut body)?;
    if chunked {
        body = dechunk(&body)?;
    }
    Ok(HttpResponse { status, headers, body })
}

fn dechunk(mut data: &[u8]) -> std::io::Result<Vec<u8>> {
    let mut out = Vec::new();
    loop {
        let pos = data.windows(2).position(|w| w == b"\r\n").ok_or_else(|| std::io::Error::other("bad chunk"))?;
        let size_str = std::str::from_utf8(&data[..pos]).map_err(std::io::Error::other)?;
        let size = usize::from_str_radix(size_str.split(';').next().unwrap_or("").trim(), 16)
            .map_err(std::io::Error::other)?;
        data = &data[pos + 2..];
        if size == 0 {
            return Ok(out);
        }
        out.extend_from_slice(&data[..size]);
        data = &data[size + 2..];
    }
}

/// POSTs a render body to /v1/render asking for a PNG; panics unless a 200 `image/png` comes back.
pub fn post_render_png(addr: SocketAddr, content_type: &str, body: &[u8], timeout: Duration) -> HttpResponse {
    let resp = http_request(
        addr,
        "POST",
        "/v1/render",
        &[("Content-Type", content_type), ("Accept", "image/png")],
        body,
        timeout,
    )
    .expect("render request");
    assert_eq!(resp.status, 200, "{}", String::from_utf8_lossy(&resp.body));
    assert_eq!(resp.header("content-type"), Some("image/png"));
    resp
}

/// The boundary of every multipart body built by `multipart`.
pub const BOUNDARY: &str = "scnerf-e2e-7d1f0b3a9c";

/// A multipart/form-data body from (name, filename, content type, bytes) parts, and its
/// Content-Type.
pub fn multipart(parts: &[(&str, Option<&str>, &str, &[u8])]) -> (String, Vec<u8>) {
    let mut body = Vec::new();
    for (name, filename, ctype, data) in parts {
        body.extend_from_slice(format!("--{BOUNDARY}\r\n").as_bytes());
        let disposition = match filename {
            Some(f) => format!("Content-Disposition: form-data; name=\"{name}\"; filename=\"{f}\"\r\n"),
            None => format!("Content-Disposition: form-data; name=\"{name}\"\r\n"),
        };
        body.extend_from_slice(disposition.as_bytes());
        body.extend_from_slice(format!("Content-Type: {ctype}\r\n\r\n").as_bytes());
        body.extend_from_slice(data);
        body.extend_from_slice(b"\r\n");
    }
    body.extend_from_slice(format!("--{BOUNDARY}--\r\n").as_bytes());
    (format!("multipart/form-data; boundary={BOUNDARY}"), body)
}

/// A render request split into its scene part (the body of `POST /v1/scenes`) and its view part
/// (`{"target", "outputs"}`, the body of `POST /v1/scenes/{id}/render`).
pub fn split_request(request: &Value) -> (Value, Value) {
    let mut scene = request.clone();
    let view = match scene.as_object_mut() {
        Some(obj) => json!({"target": obj.remove("target"), "outputs": obj.remove("outputs")}),
        None => Value::Null,
    };
    (scene, view)
}

/// A test case directory (`request.json` + `source_{i}.png`, like the parity fixtures).
pub struct Case {
    pub request: Value,
    pub images: Vec<Vec<u8>>,
}

impl Case {
    pub fn load(dir: &Path) -> std::io::Result<Case> {
        let request =
            serde_json::from_slice(&std::fs::read(dir.join("request.json"))?).map_err(std::io::Error::other)?;
        let images = (0..3).map(|i| std::fs::read(dir.join(format!("source_{i}.png")))).collect::<Result<_, _>>()?;
        Ok(Case { request, images })
    }

    /// A multipart body of `json` (the case's request, or a part or variant of it) and the case's
    /// images as parts `source_0..2`, and its Content-Type.
    pub fn multipart(&self, json: &Value) -> (String, Vec<u8>) {
        let json = serde_json::to_vec(json).expect("JSON values serialise");
        let names = ["source_0", "source_1", "source_2"];
        let mut parts: Vec<(&str, Option<&str>, &str, &[u8])> = vec![("request", None, "application/json", &json)];
        parts
            .extend(names.iter().zip(&self.images).map(|(n, img)| (*n, Some("view.png"), "image/png", img.as_slice())));
        multipart(&parts)
    }

    /// Creates the case's scene on the server; returns its id.
    pub fn create_scene(&self, addr: SocketAddr, token: &Option<String>) -> Result<String, String> {
        let (scene, _) = split_request(&self.request);
        let (ctype, body) = self.multipart(&scene);
        let auth = auth_header(token);
        let mut headers = vec![("content-type", ctype.as_str())];
        if let Some(a) = &auth {
            headers.push(("authorization", a.as_str()));
        }
        let r = http_request(addr, "POST", "/v1/scenes", &headers, &body, Duration::from_secs(600))
            .map_err(|e| format!("POST /v1/scenes: {e}"))?;
        if r.status != 201 {
            return Err(format!("POST /v1/scenes: {} {}", r.status, String::from_utf8_lossy(&r.body)));
        }
        let v: Value = serde_json::from_slice(&r.body).map_err(|e| e.to_string())?;
        v["scene_id"].as_str().map(str::to_string).ok_or_else(|| "no scene_id in the answer".into())
    }

    /// The case's target camera resized to `size` x `size` (intrinsics scaled so that pixel
    /// centres stay at integer coordinates), as a scene-render body asking for RGB.
    pub fn view_body(&self, size: u32) -> Vec<u8> {
        let mut target = self.request["target"].clone();
        let (w, h) = (target["width"].as_f64().unwrap_or(1.0), target["height"].as_f64().unwrap_or(1.0));
        let (sx, sy) = (f64::from(size) / w, f64::from(size) / h);
        let i = &mut target["intrinsics"];
        if let (Some(fx), Some(fy), Some(cx), Some(cy)) =
            (i["fx"].as_f64(), i["fy"].as_f64(), i["cx"].as_f64(), i["cy"].as_f64())
        {
            *i = json!({"fx": fx * sx, "fy": fy * sy, "cx": (cx + 0.5) * sx - 0.5, "cy": (cy + 0.5) * sy - 0.5});
        }
        target["width"] = json!(size);
        target["height"] = json!(size);
        serde_json::to_vec(&json!({"target": target, "outputs": ["rgb"]})).unwrap_or_default()
    }
}

/// Builds the server binary with the same profile as the tests and returns its path.
/// (Binaries of another package are not built for this one's tests; this is what `escargot`
/// does, without the dependency.) `SCNERF_SERVER_BIN=PATH` tests that binary instead (a
/// release build, or an older build to see a test fail before a fix).
pub fn server_binary() -> PathBuf {
    if let Some(path) = std::env::var_os("SCNERF_SERVER_BIN") {
        return PathBuf::from(path);
    }
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let mut cmd = Command::new(cargo);
    cmd.current_dir(repo_root())
        .args(["build", "-p", "scnerf-server", "--bin", "scnerf-server", "--message-format=json"])
        .stderr(Stdio::inherit());
    if !cfg!(debug_assertions) {
        cmd.arg("--release");
    }
    let output = cmd.output().expect("run cargo build");
    assert!(output.status.success(), "cargo build of scnerf-server failed");
    String::from_utf8_lossy(&output.stdout)
        .lines()
        .filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok())
        .filter(|m| m["reason"] == "compiler-artifact" && m["target"]["name"] == "scnerf-server")
        .filter_map(|m| m["executable"].as_str().map(PathBuf::from))
        .next_back()
        .expect("cargo did not report the scnerf-server executable")
}

/// A running server process, killed when dropped.
pub struct ServerProcess {
    pub child: Child,
    pub addr: SocketAddr,
}

impl ServerProcess {
    /// Starts the binary on an ephemeral loopback port and reads the bound address from stdout.
    pub fn start(binary: &Path, args: &[&str]) -> ServerProcess {
        ServerProcess::start_with_env(binary, args, &[])
    }

    /// `start` with settings in the environment (`SCNERF_*`).
    pub fn start_with_env(binary: &Path, args: &[&str], env: &[(&str, &str)]) -> ServerProcess {
        let mut child = Command::new(binary)
            .args(["--addr", "127.0.0.1:0"])
            .args(args)
            .envs(env.iter().copied())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .expect("start scnerf-server");
        let stdout = child.stdout.take().expect("stdout");
        let mut lines = BufReader::new(stdout).lines();
        let addr = loop {
            match lines.next() {
                Some(Ok(line)) => {
                    if let Some(a) = line.strip_prefix("listening on http://") {
                        break a.trim().parse().expect("bound address");
                    }
                }
                _ => {
                    let status = child.wait().ok();
                    panic!("scnerf-server exited before listening ({status:?})");
                }
            }
        };
        ServerProcess { child, addr }
    }

    /// Polls /readyz until 200 or the timeout.
    pub fn wait_ready(&mut self, timeout: Duration) {
        let start = Instant::now();
        while start.elapsed() < timeout {
            if let Ok(Some(status)) = self.child.try_wait() {
                panic!("scnerf-server exited during warm-up: {status}");
            }
            if let Ok(r) = http_request(self.addr, "GET", "/readyz", &[], b"", Duration::from_secs(5)) {
                if r.status == 200 {
                    return;
                }
            }
            std::thread::sleep(Duration::from_millis(200));
        }
        panic!("scnerf-server not ready after {timeout:?}");
    }
}

impl ServerProcess {
    /// Sends SIGTERM (what orchestrators send to stop a container).
    pub fn terminate(&self) {
        let pid = libc::pid_t::try_from(self.child.id()).expect("pid");
        // SAFETY: kill(2) with a valid signal number on our own child process.
        assert_eq!(unsafe { libc::kill(pid, libc::SIGTERM) }, 0);
    }

    /// Waits for the process to exit; panics after `timeout`.
    pub fn wait_exit(&mut self, timeout: Duration) -> std::process::ExitStatus {
        let start = Instant::now();
        loop {
            if let Some(status) = self.child.try_wait().expect("wait") {
                return status;
            }
            assert!(start.elapsed() < timeout, "the server did not exit within {timeout:?}");
            std::thread::sleep(Duration::from_millis(20));
        }
    }
}

impl Drop for ServerProcess {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Peak signal-to-noise ratio in dB of two equally long [0, 1] signals.
pub fn psnr(a: &[f32], b: &[f32]) -> f64 {
    assert_eq!(a.len(), b.len());
    let mse = a.iter().zip(b).map(|(x, y)| (f64::from(*x) - f64::from(*y)).powi(2)).sum::<f64>() / a.len() as f64;
    -10.0 * mse.log10()
}

/// The `authorization` header value for a bearer token.
pub fn auth_header(token: &Option<String>) -> Option<String> {
    token.as_ref().map(|t| format!("Bearer {t}"))
}

/// `VmHWM` (peak resident set) and `VmRSS` of a process, in KiB, from /proc (Linux).
pub fn memory_kib(pid: u32) -> Option<(u64, u64)> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let field = |name: &str| {
        status.lines().find_map(|l| l.strip_prefix(name)?.trim().strip_suffix("kB")?.trim().parse::<u64>().ok())
    };
    Some((field("VmHWM:")?, field("VmRSS:")?))
}
