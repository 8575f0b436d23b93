//! Rendering a camera path into `<out>/frames/frame_NNNN.png` and `<out>/depth/frame_NNNN.npy`,
//! resumable: frames already written are skipped, and each file is written under a temporary
//! name and renamed, so an interrupted run never leaves a partial frame behind. The path's
//! cameras are kept in `<out>/cameras.json` (API form, usable as `--path FILE`), and a run into a
//! folder holding another path's frames is refused.

use std::io::Write;
use std::path::{Path, PathBuf};

use indicatif::ProgressBar;

use crate::api::{Client, Rendered, Scene};
use crate::error::{Error, Result};
use scnerf_capture::camera::Camera;
use scnerf_capture::wire::WireCamera;

#[derive(Debug, PartialEq, Eq)]
pub struct Done {
    pub rendered: usize,
    pub skipped: usize,
}

/// Digits in frame numbers: at least 4, more for long paths.
pub fn frame_digits(count: usize) -> usize {
    count.saturating_sub(1).to_string().len().max(4)
}

pub fn frame_path(out: &Path, i: usize, digits: usize) -> PathBuf {
    out.join("frames").join(format!("frame_{i:0digits$}.png"))
}

fn depth_path(out: &Path, i: usize, digits: usize) -> PathBuf {
    out.join("depth").join(format!("frame_{i:0digits$}.npy"))
}

/// Renders every frame of `cameras` not yet in `out`; `depth` also writes depth maps.
pub fn render_frames(
    client: &Client,
    scene: &mut Scene,
    cameras: &[Camera],
    out: &Path,
    depth: bool,
    bar: &ProgressBar,
) -> Result<Done> {
    claim_folder(out, cameras)?;
    let digits = frame_digits(cameras.len());
    let todo: Vec<usize> = (0..cameras.len()).filter(|&i| !frame_path(out, i, digits).exists()).collect();
    let skipped = cameras.len() - todo.len();
    bar.set_length(cameras.len() as u64);
    bar.set_position(skipped as u64);
    bar.reset_eta();
    for &i in &todo {
        let rendered = client.render(scene, &cameras[i], depth)?;
        // depth first: a frame counts as done once its PNG exists
        if let Some(d) = &rendered.depth {
            write_npy(&depth_path(out, i, digits), d, rendered.height, rendered.width)?;
        }
        write_atomically(&frame_path(out, i, digits), &rendered.rgb_png)?;
        bar.set_message(server_summary(&rendered));
        bar.inc(1);
    }
    Ok(Done { rendered: todo.len(), skipped })
}

/// "renderer 812 ms, total 905 ms; sources 3,7,12; guided, 7.6 samples per ray": the server's
/// own view of the last frame.
pub fn server_summary(r: &Rendered) -> String {
    let timings: Vec<String> = ["encoder", "volume", "renderer", "total"]
        .iter()
        .filter_map(|k| r.timings_ms.get(*k).map(|ms| format!("{k} {ms:.0} ms")))
        .collect();
    let mut s = format!("server: {}", timings.join(", "));
    if let Some(src) = &r.sources {
        let list: Vec<String> = src.iter().map(usize::to_string).collect();
        s.push_str(&format!("; sources {}", list.join(",")));
    }
    if let Some((sampling, samples)) = &r.sampling {
        s.push_str(&format!("; {sampling}, {samples:.1} samples per ray"));
    }
    s
}

/// Writes `<out>/cameras.json`, or checks that the one there is this path's.
fn claim_folder(out: &Path, cameras: &[Camera]) -> Result<()> {
    for sub in ["frames", "depth"] {
        std::fs::create_dir_all(out.join(sub)).map_err(|e| Error::io(out.join(sub), e))?;
    }
    let file = out.join("cameras.json");
    // Through a `Value`, whose keys are sorted: the file is compared byte for byte with the one
    // there, which earlier versions of the client wrote so.
    let cameras: Vec<WireCamera> = cameras.iter().map(WireCamera::from).collect();
    let ours = serde_json::to_value(cameras).and_then(|v| serde_json::to_string_pretty(&v)).expect("cameras serialize");
    match std::fs::read_to_string(&file) {
        Ok(theirs) if theirs != ours => Err(Error::Usage(format!(
            "{} holds frames of another camera path ({} differs): use another --out, or delete that folder",
            out.display(),
            file.display()
        ))),
        Ok(_) => Ok(()),
        Err(_) => write_atomically(&file, ours.as_bytes()),
    }
}

pub fn write_atomically(path: &Path, bytes: &[u8]) -> Result<()> {
    let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let tmp = path.with_file_name(format!(".{name}.partial"));
    let write = || -> std::io::Result<()> {
        let mut f = std::fs::File::create(&tmp)?;
        f.write_all(bytes)?;
        f.sync_all()?;
        std::fs::rename(&tmp, path)
    };
    write().map_err(|e| Error::io(path, e))
}

/// A float32 (height, width) .npy file, written atomically.
pub fn write_npy(path: &Path, values: &[f32], height: u32, width: u32) -> Result<()> {
    use npyz::WriterBuilder;
    let encode = || -> std::io::Result<Vec<u8>> {
        let mut bytes = Vec::new();
        let mut writer = npyz::WriteOptions::new()
            .default_dtype()
            .shape(&[u64::from(height), u64::from(width)])
            .writer(&mut bytes)
            .begin_nd()?;
        writer.extend(values.iter().copied())?;
        writer.finish()?;
        Ok(bytes)
    };
    write_atomically(path, &encode().map_err(|e| Error::io(path, e))?)
}
