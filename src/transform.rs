//! Affine transforms of the manifest (`meshes[i].transform`), in float64.
//!
//! ```json
//! {"matrix": [1, 0, 0, 2,  0, 1, 0, 0,  0, 0, 1, 0,  0, 0, 0, 1]}
//! {"scale": 2, "rotate": {"axis": [0, 1, 0], "degrees": 90}, "translate": [0, 0, 5]}
//! ```
//!
//! A matrix is row-major and applies to column vectors (`p' = M p`). The second form applies
//! scale, then rotation (right-hand rule about the axis), then translation.

use glam::{DMat4, DVec3, DVec4};

/// The matrix of 16 row-major numbers.
pub fn from_row_major(m: &[f64; 16]) -> DMat4 {
    DMat4::from_cols_array(m).transpose()
}

/// `translate * rotate * scale`; `rotation` is a unit axis and an angle in degrees.
pub fn scale_rotate_translate(
    scale: DVec3,
    rotation: Option<(DVec3, f64)>,
    translate: DVec3,
) -> DMat4 {
    let rotate = match rotation {
        Some((axis, degrees)) => rotation_matrix(axis, degrees),
        None => DMat4::IDENTITY,
    };
    DMat4::from_translation(translate) * rotate * DMat4::from_scale(scale)
}

/// Rotation by `degrees` about the unit `axis`, counter-clockwise when the axis points at
/// the viewer (Rodrigues' formula). Quarter turns are exact: `cos(90°)` is 0, not 6e-17.
pub fn rotation_matrix(axis: DVec3, degrees: f64) -> DMat4 {
    let (sin, cos) = exact_sin_cos(degrees);
    let k = axis;
    let c1 = 1.0 - cos;
    // Columns of cos·I + sin·[k]× + (1 − cos)·k kᵀ.
    DMat4::from_cols(
        DVec4::new(
            cos + k.x * k.x * c1,
            k.y * k.x * c1 + k.z * sin,
            k.z * k.x * c1 - k.y * sin,
            0.0,
        ),
        DVec4::new(
            k.x * k.y * c1 - k.z * sin,
            cos + k.y * k.y * c1,
            k.z * k.y * c1 + k.x * sin,
            0.0,
        ),
        DVec4::new(
            k.x * k.z * c1 + k.y * sin,
            k.y * k.z * c1 - k.x * sin,
            cos + k.z * k.z * c1,
            0.0,
        ),
        DVec4::W,
    )
}

fn exact_sin_cos(degrees: f64) -> (f64, f64) {
    let turns = degrees.rem_euclid(360.0);
    match turns {
        0.0 => (0.0, 1.0),
        90.0 => (1.0, 0.0),
        180.0 => (0.0, -1.0),
        270.0 => (-1.0, 0.0),
        _ => turns.to_radians().sin_cos(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn row_major_puts_translation_in_elements_3_7_11() {
        let m = from_row_major(&[
            1.0, 0.0, 0.0, 5.0, 0.0, 1.0, 0.0, 6.0, 0.0, 0.0, 1.0, 7.0, 0.0, 0.0, 0.0, 1.0,
        ]);
        assert_eq!(m.transform_point3(DVec3::ZERO), DVec3::new(5.0, 6.0, 7.0));
    }

    #[test]
    fn rotation_follows_the_right_hand_rule() {
        // x rotated a quarter turn about z is y; y about x is z; z about y is x.
        let cases = [
            (DVec3::Z, DVec3::X, DVec3::Y),
            (DVec3::X, DVec3::Y, DVec3::Z),
            (DVec3::Y, DVec3::Z, DVec3::X),
        ];
        for (axis, from, to) in cases {
            let r = rotation_matrix(axis, 90.0);
            assert_eq!(r.transform_vector3(from), to, "axis {axis}");
        }
    }

    #[test]
    fn rotation_matches_rodrigues_for_an_arbitrary_axis() {
        let axis = DVec3::new(1.0, 2.0, 3.0).normalize();
        let v = DVec3::new(-0.5, 0.25, 2.0);
        for degrees in [-170.0, -33.0, 1e-3, 47.0, 123.0, 359.0] {
            let theta = f64::to_radians(degrees);
            let expected = v * theta.cos()
                + axis.cross(v) * theta.sin()
                + axis * axis.dot(v) * (1.0 - theta.cos());
            let got = rotation_matrix(axis, degrees).transform_vector3(v);
            assert!(
                (got - expected).length() < 1e-14,
                "{degrees}: {got} vs {expected}"
            );
        }
    }

    #[test]
    fn scale_then_rotate_then_translate() {
        let m = scale_rotate_translate(
            DVec3::new(2.0, 1.0, 1.0),
            Some((DVec3::Z, 90.0)),
            DVec3::new(5.0, 0.0, 10.0),
        );
        // (1,0,0) -> scaled (2,0,0) -> rotated (0,2,0) -> translated (5,2,10). Translated
        // off the axis, so that rotating after translating (to (0,7,10)) would show.
        assert_eq!(m.transform_point3(DVec3::X), DVec3::new(5.0, 2.0, 10.0));
    }
}
