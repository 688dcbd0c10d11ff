//! Camera files (`drape render --camera`): the engine's [`PinholeCamera`] as JSON, with
//! `near`, `far` and `background` optional. Parsing is here; the checks of the values
//! are the engine's ([`PinholeCamera::validate`]).

use drape_engine::ops::splat::scene::PinholeCamera;

/// The file's fields, as [`PinholeCamera`]'s.
#[derive(serde::Deserialize, serde::Serialize)]
struct CameraFile {
    fx: f32,
    fy: f32,
    cx: f32,
    cy: f32,
    width: u32,
    height: u32,
    rotation: [[f32; 3]; 3],
    translation: [f32; 3],
    #[serde(default = "default_near")]
    near: f32,
    #[serde(default = "default_far")]
    far: f32,
    #[serde(default)]
    background: [f32; 3],
}

fn default_near() -> f32 {
    PinholeCamera::DEFAULT_NEAR
}

fn default_far() -> f32 {
    PinholeCamera::DEFAULT_FAR
}

/// Parses a camera file's text (the values unchecked: see [`PinholeCamera::validate`]).
pub fn parse(text: &str) -> serde_json::Result<PinholeCamera> {
    let f: CameraFile = serde_json::from_str(text)?;
    Ok(PinholeCamera {
        fx: f.fx,
        fy: f.fy,
        cx: f.cx,
        cy: f.cy,
        width: f.width,
        height: f.height,
        rotation: f.rotation,
        translation: f.translation,
        near: f.near,
        far: f.far,
        background: f.background,
    })
}

/// The camera as a camera file's JSON (every field written).
pub fn to_json(cam: &PinholeCamera) -> String {
    let f = CameraFile {
        fx: cam.fx,
        fy: cam.fy,
        cx: cam.cx,
        cy: cam.cy,
        width: cam.width,
        height: cam.height,
        rotation: cam.rotation,
        translation: cam.translation,
        near: cam.near,
        far: cam.far,
        background: cam.background,
    };
    serde_json::to_string(&f).expect("a camera serialises")
}

#[cfg(test)]
mod tests {
    use drape_engine::ops::splat::scene::PinholeCamera;

    #[test]
    fn round_trip_and_defaults() {
        let cam =
            PinholeCamera::look_at([0.0, 0.0, -3.0], [0.0; 3], [0.0, -1.0, 0.0], 50.0, 64, 48)
                .unwrap();
        assert_eq!(super::parse(&super::to_json(&cam)).unwrap(), cam);
        let minimal = r#"{"fx": 50, "fy": 50, "cx": 32, "cy": 24, "width": 64, "height": 48,
            "rotation": [[1,0,0],[0,1,0],[0,0,1]], "translation": [0,0,0]}"#;
        let c = super::parse(minimal).unwrap();
        assert_eq!(
            (c.near, c.far, c.background),
            (
                PinholeCamera::DEFAULT_NEAR,
                PinholeCamera::DEFAULT_FAR,
                [0.0; 3]
            )
        );
        assert!(super::parse("{}").is_err());
    }
}
