//! The video of the rendered frames: MP4 (H.264) through `ffmpeg` when it is on PATH, otherwise
//! an animated GIF written here, with a note saying so (never silently nothing).

use std::ffi::OsStr;
use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};
use std::process::Command;

use image::codecs::gif::{GifEncoder, Repeat};
use image::{Delay, Frame};

use crate::error::{Error, Result};

#[derive(Debug)]
pub struct Video {
    pub path: PathBuf,
    /// Why the video is not an MP4, if it is not.
    pub note: Option<String>,
}

/// `ffmpeg` in one of the folders of a PATH-like list.
pub fn find_ffmpeg(path_var: Option<&OsStr>) -> Option<PathBuf> {
    let dirs = std::env::split_paths(path_var?).collect::<Vec<_>>();
    dirs.into_iter().map(|d| d.join("ffmpeg")).find(|p| p.is_file())
}

/// Writes `<out>/video.mp4` with ffmpeg if given one, else `<out>/video.gif`, from the frames
/// `<frames>/frame_%0{digits}d.png` numbered from 0.
pub fn write(frames: &Path, count: usize, digits: usize, fps: u32, out: &Path, ffmpeg: Option<&Path>) -> Result<Video> {
    match ffmpeg {
        Some(ffmpeg) => {
            let path = out.join("video.mp4");
            encode_mp4(ffmpeg, frames, digits, fps, &path)?;
            Ok(Video { path, note: None })
        }
        None => {
            let path = out.join("video.gif");
            encode_gif(frames, count, digits, fps, &path)?;
            Ok(Video {
                path,
                note: Some("ffmpeg is not on PATH: wrote an animated GIF (install ffmpeg for MP4)".into()),
            })
        }
    }
}

fn encode_mp4(ffmpeg: &Path, frames: &Path, digits: usize, fps: u32, path: &Path) -> Result<()> {
    let pattern = frames.join(format!("frame_%0{digits}d.png"));
    let output = Command::new(ffmpeg)
        .args(["-y", "-loglevel", "error", "-framerate", &fps.to_string(), "-i"])
        .arg(&pattern)
        // H.264 in yuv420p needs even sizes: pad by one pixel when odd
        .args(["-vf", "pad=ceil(iw/2)*2:ceil(ih/2)*2", "-c:v", "libx264", "-pix_fmt", "yuv420p"])
        .arg(path)
        .output()
        .map_err(|e| Error::Video(format!("cannot run {}: {e}", ffmpeg.display())))?;
    if !output.status.success() {
        let stderr = String::from_utf8_lossy(&output.stderr);
        return Err(Error::Video(format!("{} failed ({}): {}", ffmpeg.display(), output.status, stderr.trim())));
    }
    Ok(())
}

fn encode_gif(frames: &Path, count: usize, digits: usize, fps: u32, path: &Path) -> Result<()> {
    let file = File::create(path).map_err(|e| Error::io(path, e))?;
    let mut encoder = GifEncoder::new_with_speed(BufWriter::new(file), 10);
    let gif_error = |e: image::ImageError| Error::Video(format!("writing {}: {e}", path.display()));
    encoder.set_repeat(Repeat::Infinite).map_err(gif_error)?;
    let delay = Delay::from_numer_denom_ms(1000, fps.max(1));
    for i in 0..count {
        let frame_path = frames.join(format!("frame_{i:0digits$}.png"));
        let rgba = image::open(&frame_path)
            .map_err(|e| Error::Video(format!("reading {}: {e}", frame_path.display())))?
            .into_rgba8();
        encoder.encode_frame(Frame::from_parts(rgba, 0, 0, delay)).map_err(gif_error)?;
    }
    Ok(())
}
