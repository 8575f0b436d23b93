//! The API's camera as JSON (docs/design.md, "HTTP API"): what the client sends, what the server
//! parses, what `POST /v1/captures` answers with and what the OpenAPI document describes (with
//! the `openapi` feature), one type for all of them.
//!
//! A camera may be written in any of the API's conventions: `{fx, fy, cx, cy}` or a 3x3 matrix,
//! as `intrinsics` or `K`; a world-to-camera or camera-to-world pose in OpenCV or OpenGL axes.
//! [`WireCamera::from`] a canonical [`Camera`] writes the canonical form (`{fx, fy, cx, cy}`,
//! world-to-camera, OpenCV axes); the server validates a camera and converts it to that form
//! (`scnerf_server::camera`), the client reads camera files with [`crate::camera::w2c_from_api`].
//!
//! Parsing is strict, as everywhere in the API: unknown fields are refused, and so are duplicate
//! keys (serde's derived parsers refuse them; [`WireIntrinsics`], read by hand, does too).

use nalgebra::{Matrix3, Matrix4, SMatrix};
use serde::de::{Deserializer, MapAccess, SeqAccess, Visitor};
use serde::{Deserialize, Serialize};

use crate::camera::{Axes, Camera, Intrinsics, PoseKind};

/// A 3x3 matrix on the wire: rows.
pub type Rows3 = [[f64; 3]; 3];
/// A 4x4 matrix on the wire: rows.
pub type Rows4 = [[f64; 4]; 4];

/// A camera: its image size, its intrinsics (`intrinsics` or `K`) and its pose.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema), schema(as = Camera))]
pub struct WireCamera {
    #[cfg_attr(feature = "openapi", schema(minimum = 1))]
    pub width: u32,
    #[cfg_attr(feature = "openapi", schema(minimum = 1))]
    pub height: u32,
    /// `{fx, fy, cx, cy}` or a 3x3 matrix (rows); give this or `K`.
    #[serde(default, deserialize_with = "given", skip_serializing_if = "Option::is_none")]
    pub intrinsics: Option<WireIntrinsics>,
    /// 3x3 intrinsic matrix (rows), instead of `intrinsics`.
    #[serde(default, rename = "K", skip_serializing_if = "Option::is_none")]
    #[cfg_attr(feature = "openapi", schema(value_type = Option<Matrix3Rows>))]
    pub k: Option<Rows3>,
    pub pose: WirePose,
}

/// `{fx, fy, cx, cy}` or a 3x3 matrix (rows).
#[derive(Debug, Clone, PartialEq, Serialize)]
#[serde(untagged)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema), schema(as = Intrinsics))]
pub enum WireIntrinsics {
    Focal(Intrinsics),
    #[cfg_attr(feature = "openapi", schema(value_type = Matrix3Rows))]
    Matrix(Rows3),
}

/// A pose matrix and the convention it is written in.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema), schema(as = Pose))]
pub struct WirePose {
    /// 4x4, row-major (a list of 4 rows of 4 numbers).
    #[cfg_attr(feature = "openapi", schema(value_type = Matrix4Rows))]
    pub matrix: Rows4,
    #[cfg_attr(feature = "openapi", schema(value_type = String, pattern = "^(world_to_camera|camera_to_world)$"))]
    pub kind: PoseKind,
    #[cfg_attr(feature = "openapi", schema(value_type = String, pattern = "^(opencv|opengl)$"))]
    pub axes: Axes,
}

/// A camera that gives both `intrinsics` and `K`, or neither.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum IntrinsicsError {
    #[error("give either intrinsics or K, not both")]
    Both,
    #[error("missing field `intrinsics` (or `K`)")]
    Missing,
}

impl IntrinsicsError {
    /// The camera's field the error is about.
    pub fn field(self) -> &'static str {
        match self {
            IntrinsicsError::Both => "K",
            IntrinsicsError::Missing => "intrinsics",
        }
    }
}

impl From<&Camera> for WireCamera {
    /// The canonical form: `{fx, fy, cx, cy}`, world-to-camera, OpenCV axes.
    fn from(c: &Camera) -> WireCamera {
        let pose =
            WirePose { matrix: to_rows(&c.w2c.to_homogeneous()), kind: PoseKind::WorldToCamera, axes: Axes::Opencv };
        WireCamera {
            width: c.width,
            height: c.height,
            intrinsics: Some(WireIntrinsics::Focal(c.intrinsics)),
            k: None,
            pose,
        }
    }
}

impl WireCamera {
    /// The intrinsic matrix, from whichever of `intrinsics` and `K` the camera gives: one must be.
    pub fn intrinsic_matrix(&self) -> Result<Matrix3<f64>, IntrinsicsError> {
        match (&self.intrinsics, &self.k) {
            (Some(i), None) => Ok(i.matrix()),
            (None, Some(k)) => Ok(from_rows(k)),
            (Some(_), Some(_)) => Err(IntrinsicsError::Both),
            (None, None) => Err(IntrinsicsError::Missing),
        }
    }
}

impl WireIntrinsics {
    /// The intrinsic matrix (of the focal form: [`Intrinsics::k`]).
    pub fn matrix(&self) -> Matrix3<f64> {
        match self {
            WireIntrinsics::Focal(i) => i.k(),
            WireIntrinsics::Matrix(rows) => from_rows(rows),
        }
    }
}

/// A square matrix from its rows: matrices are row-major on the wire, as in docs/design.md
/// (nalgebra's own conversion from nested arrays reads columns).
pub fn from_rows<const N: usize>(rows: &[[f64; N]; N]) -> SMatrix<f64, N, N> {
    SMatrix::from_fn(|r, c| rows[r][c])
}

fn to_rows(m: &Matrix4<f64>) -> Rows4 {
    std::array::from_fn(|r| std::array::from_fn(|c| m[(r, c)]))
}

/// `intrinsics`, when the camera has the field: its value must be intrinsics (`null` is refused
/// like any other value, not read as leaving the field out).
fn given<'de, D: Deserializer<'de>>(d: D) -> Result<Option<WireIntrinsics>, D::Error> {
    WireIntrinsics::deserialize(d).map(Some)
}

/// Read straight from the document by the shape of the value (not through `serde_json::Value`,
/// whose maps keep the last of duplicate keys, nor `#[serde(untagged)]`, which buffers the value
/// the same way), so that a duplicate `fx` is refused like every other duplicate field.
impl<'de> Deserialize<'de> for WireIntrinsics {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<WireIntrinsics, D::Error> {
        d.deserialize_any(FocalOrMatrix)
    }
}

struct FocalOrMatrix;

impl<'de> Visitor<'de> for FocalOrMatrix {
    type Value = WireIntrinsics;

    fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        f.write_str("{fx, fy, cx, cy} or a 3x3 matrix")
    }

    fn visit_seq<A: SeqAccess<'de>>(self, seq: A) -> Result<WireIntrinsics, A::Error> {
        Rows3::deserialize(serde::de::value::SeqAccessDeserializer::new(seq)).map(WireIntrinsics::Matrix)
    }

    fn visit_map<A: MapAccess<'de>>(self, map: A) -> Result<WireIntrinsics, A::Error> {
        Intrinsics::deserialize(serde::de::value::MapAccessDeserializer::new(map)).map(WireIntrinsics::Focal)
    }
}

/// Schema of a 3x3 matrix ([`Rows3`]).
#[cfg(feature = "openapi")]
pub struct Matrix3Rows;

/// Schema of a 4x4 matrix ([`Rows4`]).
#[cfg(feature = "openapi")]
pub struct Matrix4Rows;

/// An `n` x `n` matrix as `n` rows of `n` numbers (what serde's fixed-size arrays accept).
#[cfg(feature = "openapi")]
fn square_matrix_schema(n: usize) -> utoipa::openapi::schema::Array {
    use utoipa::openapi::schema::{ArrayBuilder, ObjectBuilder, Type};
    let row =
        ArrayBuilder::new().items(ObjectBuilder::new().schema_type(Type::Number)).min_items(Some(n)).max_items(Some(n));
    ArrayBuilder::new().items(row).min_items(Some(n)).max_items(Some(n)).build()
}

#[cfg(feature = "openapi")]
impl utoipa::PartialSchema for Matrix3Rows {
    fn schema() -> utoipa::openapi::RefOr<utoipa::openapi::schema::Schema> {
        square_matrix_schema(3).into()
    }
}

#[cfg(feature = "openapi")]
impl utoipa::ToSchema for Matrix3Rows {}

#[cfg(feature = "openapi")]
impl utoipa::PartialSchema for Matrix4Rows {
    fn schema() -> utoipa::openapi::RefOr<utoipa::openapi::schema::Schema> {
        square_matrix_schema(4).into()
    }
}

#[cfg(feature = "openapi")]
impl utoipa::ToSchema for Matrix4Rows {}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::look_at;
    use nalgebra::{Point3, Vector3};

    fn camera() -> Camera {
        Camera {
            width: 8,
            height: 6,
            intrinsics: Intrinsics { fx: 8.5, fy: 9.0, cx: 3.5, cy: 2.5 },
            w2c: look_at(&Point3::new(1.0, 2.0, 3.0), &Point3::new(0.0, 0.5, 0.0), &Vector3::z()),
        }
    }

    fn parse(json: &str) -> Result<WireCamera, serde_json::Error> {
        serde_json::from_str(json)
    }

    #[test]
    fn a_canonical_camera_is_written_in_the_canonical_form() {
        let c = camera();
        let json = serde_json::to_value(WireCamera::from(&c)).unwrap();
        assert_eq!(json["intrinsics"], serde_json::json!({"fx": 8.5, "fy": 9.0, "cx": 3.5, "cy": 2.5}));
        assert_eq!(
            (json["pose"]["kind"].as_str(), json["pose"]["axes"].as_str()),
            (Some("world_to_camera"), Some("opencv"))
        );
        assert!(json.get("K").is_none(), "{json}");
        let m = c.w2c.to_homogeneous();
        assert_eq!(json["pose"]["matrix"][1][3].as_f64(), Some(m[(1, 3)]), "rows, not columns");
    }

    #[test]
    fn a_written_camera_reads_back_as_itself() {
        let c = camera();
        let wire = WireCamera::from(&c);
        let back = parse(&serde_json::to_string(&wire).unwrap()).unwrap();
        assert_eq!((back.width, back.height, back.intrinsic_matrix()), (8, 6, Ok(c.k())));
        assert_eq!((back.pose.kind, back.pose.axes), (PoseKind::WorldToCamera, Axes::Opencv));
        // serde_json reads a number back to within an ulp (its exact parser is a feature left off).
        assert!((from_rows(&back.pose.matrix) - c.w2c.to_homogeneous()).amax() < 1e-15);
    }

    #[test]
    fn intrinsics_are_focal_lengths_or_a_matrix_given_once() {
        let pose = r#""pose": {"matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]], "kind": "world_to_camera", "axes": "opencv"}"#;
        let k = Intrinsics { fx: 8.0, fy: 8.0, cx: 4.0, cy: 3.0 }.k();
        for intrinsics in [
            r#""intrinsics": {"fx": 8, "fy": 8, "cx": 4, "cy": 3}"#,
            r#""intrinsics": [[8, 0, 4], [0, 8, 3], [0, 0, 1]]"#,
            r#""K": [[8, 0, 4], [0, 8, 3], [0, 0, 1]]"#,
        ] {
            let c = parse(&format!(r#"{{"width": 8, "height": 6, {intrinsics}, {pose}}}"#)).unwrap();
            assert_eq!(c.intrinsic_matrix(), Ok(k), "{intrinsics}");
        }
        let both = r#""intrinsics": {"fx": 8, "fy": 8, "cx": 4, "cy": 3}, "K": [[8, 0, 4], [0, 8, 3], [0, 0, 1]]"#;
        let both = parse(&format!(r#"{{"width": 8, "height": 6, {both}, {pose}}}"#)).unwrap();
        assert_eq!(both.intrinsic_matrix().map_err(IntrinsicsError::field), Err("K"));
        let neither = parse(&format!(r#"{{"width": 8, "height": 6, {pose}}}"#)).unwrap();
        assert_eq!(neither.intrinsic_matrix().map_err(IntrinsicsError::field), Err("intrinsics"));
    }

    #[test]
    fn duplicate_keys_unknown_fields_and_null_intrinsics_are_refused() {
        let pose = r#""pose": {"matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]], "kind": "world_to_camera", "axes": "opencv"}"#;
        for (intrinsics, why) in [
            (r#""intrinsics": {"fx": 8, "fx": 9, "fy": 8, "cx": 4, "cy": 3}"#, "duplicate field `fx`"),
            (r#""intrinsics": {"fx": 8, "fy": 8, "cx": 4, "cy": 3, "skew": 0}"#, "unknown field `skew`"),
            (r#""intrinsics": null"#, "expected {fx, fy, cx, cy} or a 3x3 matrix"),
            (r#""intrinsics": [[8, 0, 4], [0, 8, 3]]"#, "invalid length 2"),
            (
                r#""K": [[8, 0, 4], [0, 8, 3], [0, 0, 1]], "K": [[8, 0, 4], [0, 8, 3], [0, 0, 1]]"#,
                "duplicate field `K`",
            ),
        ] {
            let err = parse(&format!(r#"{{"width": 8, "height": 6, {intrinsics}, {pose}}}"#)).unwrap_err();
            assert!(err.to_string().contains(why), "{intrinsics}: {err}");
        }
    }
}
