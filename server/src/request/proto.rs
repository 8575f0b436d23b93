//! The protobuf wire form (`scnerf.v1` messages of the `scnerf-proto` crate).

use bytes::Bytes;
use prost::Message;
use scnerf_capture::camera::Intrinsics;
use scnerf_proto::v1 as pb;

use super::{Limits, OutputKind, RenderRequest, SceneRequest, SourceSpec, TargetRequest};
use nalgebra::SMatrix;

use super::cameras::{Axes, CameraSpec, PoseKind, PoseSpec};
use crate::error::ApiError;

impl RenderRequest {
    /// Parses the protobuf form.
    pub fn from_protobuf(body: &[u8], limits: &Limits) -> Result<RenderRequest, ApiError> {
        request_from_proto(decode(body, &[sources(limits), OUTPUTS], "RenderRequest")?)
    }
}

impl SceneRequest {
    pub fn from_protobuf(body: &[u8], limits: &Limits) -> Result<SceneRequest, ApiError> {
        scene_from_proto(decode(body, &[sources(limits)], "SceneRequest")?)
    }
}

impl TargetRequest {
    pub fn from_protobuf(body: &[u8]) -> Result<TargetRequest, ApiError> {
        let msg: pb::SceneRenderRequest = decode(body, &[OUTPUTS, PINNED], "SceneRenderRequest")?;
        Ok(TargetRequest {
            target: camera_from_proto(msg.target, "target")?,
            outputs: outputs_from_proto(&msg.outputs)?,
            sources: (!msg.sources.is_empty()).then_some(msg.sources),
            sampling: (!msg.sampling.is_empty()).then_some(msg.sampling),
            model: named(msg.model),
        })
    }
}

/// A proto3 string field left empty means no model named (the default).
fn named(model: String) -> Option<String> {
    (!model.is_empty()).then_some(model)
}

/// Decodes message `name` once its repeated fields are within `bounds`.
fn decode<M: Message + Default>(body: &[u8], bounds: &[Bound], name: &str) -> Result<M, ApiError> {
    check_repeated(body, bounds)?;
    M::decode(body).map_err(|e| ApiError::malformed(Some("body".to_string()), format!("invalid protobuf {name}: {e}")))
}

/// A repeated field of the request messages: number, name, most entries a request can use.
type Bound = (u64, &'static str, usize);
/// Field numbers are shared by RenderRequest, SceneRequest and SceneRenderRequest.
fn sources(limits: &Limits) -> Bound {
    (1, "sources", limits.max_scene_views)
}
const OUTPUTS: Bound = (6, "outputs", 3);
/// SceneRenderRequest's pinned views, when sent unpacked (packed, they are one entry of a body
/// bounded by `--max-json-bytes`).
const PINNED: Bound = (7, "sources", 3);

/// Refuses a message whose repeated fields hold more entries than a request can use, before
/// prost materialises them: an empty `sources` entry is 2 bytes on the wire and a struct of
/// ~150 bytes in memory (63 MiB of them took 3.5 GB). One pass over the top-level fields in
/// constant memory; malformed wire data ends the pass and is left to prost to report.
fn check_repeated(body: &[u8], bounds: &[Bound]) -> Result<(), ApiError> {
    let mut counts = vec![0usize; bounds.len()];
    let mut buf = body;
    while let Some(key) = varint(&mut buf) {
        let skipped = match key & 7 {
            0 => varint(&mut buf).map(drop),
            1 => skip(&mut buf, 8),
            2 => varint(&mut buf).and_then(|len| skip(&mut buf, usize::try_from(len).ok()?)),
            5 => skip(&mut buf, 4),
            _ => None,
        };
        if skipped.is_none() {
            break;
        }
        let Some(i) = bounds.iter().position(|b| b.0 == key >> 3) else { continue };
        counts[i] += 1;
        if counts[i] > bounds[i].2 {
            let (_, name, max) = bounds[i];
            return Err(ApiError::invalid(name, format!("a request carries at most {max} {name} entries")));
        }
    }
    Ok(())
}

/// A base-128 varint (at most 10 bytes), advancing `buf`.
fn varint(buf: &mut &[u8]) -> Option<u64> {
    let mut value = 0u64;
    for (i, &b) in buf.iter().take(10).enumerate() {
        value |= u64::from(b & 0x7f) << (7 * i);
        if b & 0x80 == 0 {
            *buf = &buf[i + 1..];
            return Some(value);
        }
    }
    None
}

fn skip(buf: &mut &[u8], n: usize) -> Option<()> {
    *buf = buf.get(n..)?;
    Some(())
}

fn request_from_proto(msg: pb::RenderRequest) -> Result<RenderRequest, ApiError> {
    let scene = SceneRequest {
        sources: sources_from_proto(msg.sources)?,
        near: msg.near,
        far: msg.far,
        background: (!msg.background.is_empty()).then_some(msg.background),
        model: named(msg.model),
    };
    let view = TargetRequest {
        target: camera_from_proto(msg.target, "target")?,
        outputs: outputs_from_proto(&msg.outputs)?,
        sources: None,
        sampling: (!msg.sampling.is_empty()).then_some(msg.sampling),
        model: None,
    };
    Ok(RenderRequest { scene, view })
}

fn scene_from_proto(msg: pb::SceneRequest) -> Result<SceneRequest, ApiError> {
    Ok(SceneRequest {
        sources: sources_from_proto(msg.sources)?,
        near: msg.near,
        far: msg.far,
        background: (!msg.background.is_empty()).then_some(msg.background),
        model: named(msg.model),
    })
}

fn sources_from_proto(sources: Vec<pb::Source>) -> Result<Vec<SourceSpec>, ApiError> {
    let mut out = Vec::with_capacity(sources.len());
    for (i, s) in sources.into_iter().enumerate() {
        let field = format!("sources[{i}]");
        let camera = camera_from_proto(s.camera, &format!("{field}.camera"))?;
        let image = (!s.image.is_empty()).then(|| Bytes::from(s.image));
        out.push(SourceSpec { camera, image, image_field: format!("{field}.image") });
    }
    Ok(out)
}

fn outputs_from_proto(outputs: &[String]) -> Result<Option<Vec<OutputKind>>, ApiError> {
    if outputs.is_empty() {
        return Ok(None);
    }
    let mut kinds = Vec::with_capacity(outputs.len());
    for (i, o) in outputs.iter().enumerate() {
        kinds.push(OutputKind::parse(o).ok_or_else(|| {
            ApiError::malformed(format!("outputs[{i}]"), format!("unknown output \"{o}\" (rgb, depth, opacity)"))
        })?);
    }
    Ok(Some(kinds))
}

fn camera_from_proto(c: Option<pb::Camera>, field: &str) -> Result<CameraSpec, ApiError> {
    let c = c.ok_or_else(|| ApiError::malformed(field.to_string(), "missing camera"))?;
    let k = match c.intrinsics_kind {
        Some(pb::camera::IntrinsicsKind::Intrinsics(i)) => Intrinsics { fx: i.fx, fy: i.fy, cx: i.cx, cy: i.cy }.k(),
        Some(pb::camera::IntrinsicsKind::K(m)) => matrix(&m.values, &format!("{field}.k.values"))?,
        None => return Err(ApiError::malformed(format!("{field}.intrinsics"), "missing intrinsics (or k)")),
    };
    let pose = c.pose.ok_or_else(|| ApiError::malformed(format!("{field}.pose"), "missing pose"))?;
    let kind = match pb::PoseKind::try_from(pose.kind) {
        Ok(pb::PoseKind::WorldToCamera) => PoseKind::WorldToCamera,
        Ok(pb::PoseKind::CameraToWorld) => PoseKind::CameraToWorld,
        _ => {
            return Err(ApiError::malformed(
                format!("{field}.pose.kind"),
                "kind must be WORLD_TO_CAMERA or CAMERA_TO_WORLD",
            ))
        }
    };
    let axes = match pb::Axes::try_from(pose.axes) {
        Ok(pb::Axes::Opencv) => Axes::Opencv,
        Ok(pb::Axes::Opengl) => Axes::Opengl,
        _ => return Err(ApiError::malformed(format!("{field}.pose.axes"), "axes must be OPENCV or OPENGL")),
    };
    Ok(CameraSpec {
        width: c.width,
        height: c.height,
        k,
        pose: PoseSpec { matrix: matrix(&pose.matrix, &format!("{field}.pose.matrix"))?, kind, axes },
    })
}

/// An N x N matrix from its N² values, row by row.
fn matrix<const N: usize>(v: &[f64], field: &str) -> Result<SMatrix<f64, N, N>, ApiError> {
    if v.len() != N * N {
        return Err(ApiError::malformed(
            field.to_string(),
            format!("expected {} values (row-major {N}x{N}), got {}", N * N, v.len()),
        ));
    }
    Ok(SMatrix::from_row_slice(v))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn protobuf_repeated_fields_are_counted_before_decoding() {
        let limits = Limits { max_scene_views: 16, ..Limits::default() };
        let empty_sources = [0x0a, 0x00].repeat(17);
        let err = RenderRequest::from_protobuf(&empty_sources, &limits).unwrap_err();
        assert_eq!((err.status().as_u16(), err.field()), (422, Some("sources")));
        // Other fields in between are skipped by wire type: varint, 64-bit, bytes, 32-bit.
        let mut outputs = vec![0x18, 0x96, 0x01, 0x21, 0, 0, 0, 0, 0, 0, 0, 0, 0x2d, 0, 0, 0, 0];
        outputs.extend([0x32, 0x03, b'r', b'g', b'b'].repeat(4));
        let err = TargetRequest::from_protobuf(&outputs).unwrap_err();
        assert_eq!(err.field(), Some("outputs"));
        assert!(check_repeated(&[0x0a, 0x00].repeat(16), &[sources(&limits)]).is_ok());
        // Truncated input is prost's to report.
        assert!(check_repeated(&[0x0a, 0x05, 0x00], &[sources(&limits)]).is_ok());
        // Pinned views sent unpacked, one varint each: at most 3 entries.
        let err = TargetRequest::from_protobuf(&[0x38, 0x01].repeat(4)).unwrap_err();
        assert_eq!(err.field(), Some("sources"));
    }
}
