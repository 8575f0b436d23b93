//! `scnerf eval`: held-out captured views rendered from the others and scored, with the protocol
//! of `scnerf-export eval` so the figures compare: per target, the 3 views of the source pool
//! (every view that is not a target) nearest by camera-centre distance
//! ([`scnerf_capture::camera::rank_sources`]), or fixed `--sources`; each source triple is
//! uploaded once as a scene of exactly those three views (reference first); targets may be
//! rendered at 1/n of their size against the box-averaged ground truth; PSNR and SSIM as
//! `exporter/scnerf_export/evaluate/metrics.py`.

use std::time::Instant;

use crate::api::{Client, Upload};
use crate::args::EvalArgs;
use crate::error::{read_bytes, Error, Result};
use crate::metrics::{error_png, psnr, ssim, Image};
use crate::render::write_atomically;
use scnerf_capture::camera::rank_sources;
use scnerf_capture::readers::{Capture, CapturedView};
use scnerf_capture::upload::image_bytes;

struct Row {
    view: String,
    sources: Vec<String>,
    psnr: f64,
    ssim: f64,
    seconds: f64,
}

/// Scores the targets of `capture` at its sizes, rendered from sources uploaded as the same
/// views of `fitted` (`capture` fitted to the server's source limit).
pub fn run(client: &Client, capture: &Capture, fitted: &Capture, args: &EvalArgs) -> Result<()> {
    let targets = targets(capture, args)?;
    let pool: Vec<&CapturedView> = capture.views.iter().filter(|v| !targets.iter().any(|t| t.name == v.name)).collect();
    let n = args.downscale;
    // (source triple, its targets), triples in order of first use
    let mut groups: Vec<(Vec<&CapturedView>, Vec<&CapturedView>)> = Vec::new();
    for target in &targets {
        let (w, h) = (target.camera.width, target.camera.height);
        if w % n != 0 || h % n != 0 {
            return Err(Error::Usage(format!("--downscale {n} does not divide {}'s size {w}x{h}", target.name)));
        }
        let sources = match &args.sources {
            Some(names) => source_views(capture, names)?,
            None => nearest(target, &pool)?,
        };
        match groups.iter_mut().find(|(s, _)| names(s) == names(&sources)) {
            Some((_, ts)) => ts.push(target),
            None => groups.push((sources, vec![target])),
        }
    }
    let mut rows = Vec::new();
    for (sources, group) in &groups {
        let uploaded = sources.iter().map(|v| fitted.view(&v.name)).collect::<scnerf_capture::Result<Vec<_>>>()?;
        let mut scene = client.create_scene(Upload::new(fitted, &uploaded))?;
        for target in group {
            let (w, h) = (target.camera.width, target.camera.height);
            let started = Instant::now();
            let rendered = client.render(&mut scene, &target.camera.resized(w / n, h / n), false)?;
            let seconds = started.elapsed().as_secs_f64();
            let pred = Image::decode(&rendered.rgb_png, capture.background).map_err(|e| Error::Response {
                context: format!("the image of {}", target.name),
                message: e.to_string(),
            })?;
            let photo = read_bytes(&target.image_path)?;
            let gt = Image::decode(&image_bytes(target, &photo, capture.background)?, capture.background)
                .map_err(|e| Error::dataset(&target.image_path, format!("cannot decode: {e}")))?
                .downscaled(n as usize);
            if let Some(dir) = &args.out {
                std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
                let name = target.name.replace('/', "_");
                write_atomically(&dir.join(format!("{name}.png")), &rendered.rgb_png)?;
                write_atomically(&dir.join(format!("{name}.error.png")), &error_png(&pred, &gt)?)?;
            }
            let row = Row {
                view: target.name.clone(),
                sources: names(sources),
                psnr: psnr(&pred, &gt)?,
                ssim: ssim(&pred, &gt)?,
                seconds,
            };
            say!("{}", format_row(&row));
            rows.push(row);
        }
    }
    let count = rows.len() as f64;
    let mean = Row {
        view: "mean".into(),
        sources: Vec::new(),
        psnr: rows.iter().map(|r| r.psnr).sum::<f64>() / count,
        ssim: rows.iter().map(|r| r.ssim).sum::<f64>() / count,
        seconds: rows.iter().map(|r| r.seconds).sum::<f64>() / count,
    };
    say!("{}", format_row(&mean));
    Ok(())
}

/// The views `--sources` names: exactly three, the first the reference.
pub(crate) fn source_views<'a>(capture: &'a Capture, names: &[String]) -> Result<Vec<&'a CapturedView>> {
    if names.len() != 3 {
        return Err(Error::Usage(format!("--sources needs 3 view names, got {}", names.len())));
    }
    Ok(names.iter().map(|n| capture.view(n)).collect::<scnerf_capture::Result<_>>()?)
}

fn names(views: &[&CapturedView]) -> Vec<String> {
    views.iter().map(|v| v.name.clone()).collect()
}

/// `--targets`, or every `--holdout`-th view.
fn targets<'a>(capture: &'a Capture, args: &EvalArgs) -> Result<Vec<&'a CapturedView>> {
    let targets: Vec<&CapturedView> = match (&args.targets, args.holdout) {
        (Some(names), _) => names.iter().map(|n| capture.view(n)).collect::<scnerf_capture::Result<_>>()?,
        (None, Some(k)) if k >= 1 => capture.views.iter().step_by(k).collect(),
        _ => return Err(Error::Usage("--holdout must be at least 1 (or give --targets)".into())),
    };
    if capture.views.len() - targets.len() < 3 {
        return Err(Error::Usage(format!(
            "{} of {} views held out: fewer than 3 are left as sources",
            targets.len(),
            capture.views.len()
        )));
    }
    Ok(targets)
}

/// The 3 pool views nearest the target that face its way, nearest first.
fn nearest<'a>(target: &CapturedView, pool: &[&'a CapturedView]) -> Result<Vec<&'a CapturedView>> {
    let candidates: Vec<_> = pool.iter().map(|v| v.camera.viewpoint()).collect();
    let ranked = rank_sources(&target.camera.viewpoint(), &candidates);
    if ranked.len() < 3 {
        return Err(Error::Usage(format!(
            "view {}: only {} source views face its way, 3 needed",
            target.name,
            ranked.len()
        )));
    }
    Ok(ranked[..3].iter().map(|&i| pool[i]).collect())
}

/// As `exporter/scnerf_export/evaluate/eval.py::format_row` (without its masked columns).
fn format_row(r: &Row) -> String {
    format!("{:>8}  {:>12}  PSNR {:6.2}  SSIM {:.3}  {:.1} s", r.view, r.sources.join(","), r.psnr, r.ssim, r.seconds)
}
