//! Reading a scene manifest: JSON text in, a checked [`Manifest`] out.
//!
//! This module only describes a scene; nothing here loads meshes or builds acceleration
//! structures (see [`crate::scene`]). Every key, default and check of the manifest format
//! (version 1) lives here. The smallest manifest renders the seed's scene:
//!
//! ```json
//! {"image": {"width": 640, "height": 480}, "spheres": [{"center": [0, 0, 3], "radius": 1}]}
//! ```
//!
//! A fuller one:
//!
//! ```json
//! {
//!   "version": 1,
//!   "image": {"width": 320, "height": 240},
//!   "output": "out/room.pfm",
//!   "camera": {"look_from": [0, 1, 5], "look_at": [0, 0, 0], "vfov": 40},
//!   "tmin": 0, "tmax": null,
//!   "background": [0.1, 0.1, 0.1],
//!   "integrator": {"type": "depth", "scale": 10},
//!   "sampler": {"type": "stratified", "spp": 16, "seed": 7},
//!   "materials": {"red": {"type": "diffuse", "albedo": [0.8, 0.1, 0.1]}},
//!   "spheres": [{"center": [0, 0, 0], "radius": 1, "material": "red"}],
//!   "planes": [{"point": [0, -1, 0], "normal": [0, 1, 0]}],
//!   "meshes": [{"file": "bunny.obj", "transform": {"scale": 2, "translate": [1, 0, 0]}}],
//!   "lights": [{"type": "point", "position": [0, 5, 0], "intensity": [10, 10, 10]}]
//! }
//! ```
//!
//! Unknown keys are errors. Refusals name the place: a line and column for JSON that does
//! not parse or has the wrong shape, a key path such as `spheres[2].radius` for values
//! that break a rule.

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};

use glam::{DMat4, DVec3};
use serde::Deserialize;

use crate::camera::{self, CameraFrame, ThinLens};
use crate::error::{ManifestError, shown};
use crate::transform;

/// Largest magnitude accepted for a coordinate, length or colour. Geometry is intersected
/// in float32 (whose edge-function products must not overflow) and in float64 (whose
/// squared distances must not), so far larger values could only produce wrong images.
pub const MAX_MAGNITUDE: f64 = 1.0e15;

/// Largest accepted image side, in pixels.
pub const MAX_IMAGE_SIDE: u32 = 65_536;

/// Largest accepted pixel count (width × height): 2^28, a 16384 × 16384 image.
pub const MAX_PIXELS: u64 = 1 << 28;

/// Largest accepted samples per pixel.
pub const MAX_SPP: u32 = 1 << 20;

/// A linear RGB triple.
pub type Rgb = [f64; 3];

/// A checked manifest: every default filled in, every rule enforced, paths resolved
/// against the manifest's folder.
#[derive(Debug, Clone, PartialEq)]
pub struct Manifest {
    /// The manifest file this came from (as given, not canonicalized).
    pub source: PathBuf,
    pub width: u32,
    pub height: u32,
    /// Where the image goes, resolved against the manifest's folder.
    pub output: PathBuf,
    pub format: OutputFormat,
    pub encoding: Encoding,
    pub camera: CameraDesc,
    /// A hit counts only if `tmin < t < tmax`; `0 <= tmin < tmax`, `tmax` may be infinite.
    pub tmin: f64,
    pub tmax: f64,
    pub background: Rgb,
    pub integrator: IntegratorDesc,
    pub sampler: SamplerDesc,
    /// Named materials, in name order; primitives refer to them by index.
    pub materials: Vec<Material>,
    pub spheres: Vec<SphereDesc>,
    pub planes: Vec<PlaneDesc>,
    pub meshes: Vec<MeshDesc>,
    pub lights: Vec<Light>,
}

/// The image file format, picked by the output's extension.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum OutputFormat {
    /// `.ppm`: 8-bit RGB, `P3` (text) or `P6` (bytes).
    Ppm(PpmStyle),
    /// `.pfm`: float32 RGB, bottom row first, always linear.
    Pfm,
}

/// `"ppm"`: the flavour of PPM written.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum PpmStyle {
    /// `P3`: decimal text.
    Plain,
    /// `P6`: raw bytes.
    Binary,
}

/// `"encoding"`: the transfer function applied before quantizing to 8 bits.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Encoding {
    Linear,
    Srgb,
}

/// The camera, reduced to the basis form (see [`crate::camera`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CameraDesc {
    pub frame: CameraFrame,
    /// `None` for a pinhole (`aperture` 0).
    pub lens: Option<ThinLens>,
}

/// `"integrator"`: what each camera ray computes.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum IntegratorDesc {
    /// `[1,1,1]` on any hit, else the background.
    Hit,
    /// `[t,t,t] / scale` for the closest hit, else the background.
    Depth { scale: f64 },
    /// `0.5 * (n + 1)` for the unit geometric normal of the closest hit.
    Normal,
    /// Mitsuba's `direct`: emission plus one bounce of direct lighting.
    Direct,
    /// Whitted ray tracing with mirror and dielectric recursion up to `max_depth`.
    Whitted { max_depth: u32 },
    /// Unbiased path tracing; `max_depth` as in Mitsuba 3 (`None`: unbounded).
    Path { max_depth: Option<u32> },
}

impl IntegratorDesc {
    /// The name used in manifests.
    pub fn name(&self) -> &'static str {
        match self {
            IntegratorDesc::Hit => "hit",
            IntegratorDesc::Depth { .. } => "depth",
            IntegratorDesc::Normal => "normal",
            IntegratorDesc::Direct => "direct",
            IntegratorDesc::Whitted { .. } => "whitted",
            IntegratorDesc::Path { .. } => "path",
        }
    }
}

/// `"sampler"`: where in each pixel the samples go.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SamplerDesc {
    pub kind: SamplerKind,
    /// Samples per pixel, at least 1 (exactly 1 for `center`).
    pub spp: u32,
    pub seed: u64,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SamplerKind {
    /// One sample at the pixel centre.
    Center,
    /// Uniform random positions.
    Independent,
    /// One jittered sample per cell of a near-square grid of `spp` cells.
    Stratified,
}

/// A named material. Colours are linear RGB.
#[derive(Debug, Clone, PartialEq)]
pub struct Material {
    pub name: String,
    pub kind: MaterialKind,
    /// Radiance leaving the front side; zero for non-emitters.
    pub emission: Rgb,
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub enum MaterialKind {
    /// Lambertian, BRDF `albedo / π`.
    Diffuse { albedo: Rgb },
    /// Perfect specular reflection.
    Mirror { reflectance: Rgb },
    /// Smooth glass with relative index of refraction `ior`.
    Dielectric { ior: f64 },
}

/// An index into [`Manifest::materials`].
pub type MaterialId = usize;

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SphereDesc {
    pub center: DVec3,
    pub radius: f64,
    pub material: Option<MaterialId>,
}

/// An infinite plane, hit from both sides.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlaneDesc {
    pub point: DVec3,
    /// Unit length.
    pub normal: DVec3,
    pub material: Option<MaterialId>,
}

#[derive(Debug, Clone, PartialEq)]
pub struct MeshDesc {
    /// Resolved against the manifest's folder.
    pub file: PathBuf,
    /// Object to world, affine.
    pub transform: DMat4,
    pub material: Option<MaterialId>,
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Light {
    /// Radiant intensity `intensity` at `position`: irradiance `I cos θ / d²`.
    Point { position: DVec3, intensity: Rgb },
    /// Light travelling along `direction` (unit), `irradiance` on a surface facing it.
    Directional { direction: DVec3, irradiance: Rgb },
}

impl Manifest {
    /// The camera rays a render of the manifest traces: every sample of every pixel.
    pub fn camera_rays(&self) -> u64 {
        u64::from(self.width) * u64::from(self.height) * u64::from(self.sampler.spp)
    }

    /// Reads and checks the manifest at `path`.
    pub fn load(path: &Path) -> Result<Manifest> {
        let text = std::fs::read(path).map_err(ManifestError::Read)?;
        Manifest::parse(&text, path)
    }

    /// Checks manifest `text` as if it had been read from `path` (which resolves the
    /// manifest's relative paths and its default output name).
    pub fn parse(text: &[u8], path: &Path) -> Result<Manifest> {
        let text = text.strip_prefix(b"\xEF\xBB\xBF").unwrap_or(text);
        // Read plainly first; only a manifest that fails is read again, tracking the path
        // of the value being read, to name the failing key. (Tracking it for every value
        // read slowed a manifest of many spheres: BENCHMARKS.md, history.)
        let raw = match serde_json::from_slice::<raw::Object<raw::Manifest>>(text) {
            Ok(raw::Object(raw)) => raw,
            Err(error) => return Err(json_failure(text, error)),
        };
        validate(raw, path)
    }
}

/// Why `text`, which serde_json rejected with `error`, fails, and at which key: read
/// again, tracking the path of the value being read.
fn json_failure(text: &[u8], error: serde_json::Error) -> ManifestError {
    let mut deserializer = serde_json::Deserializer::from_slice(text);
    match serde_path_to_error::deserialize::<_, raw::Object<raw::Manifest>>(&mut deserializer) {
        Err(tracked) => json_error(known_keys(tracked.path()), tracked.into_inner()),
        // After the value: trailing text, which has no key.
        Ok(_) => json_error(String::new(), deserializer.end().err().unwrap_or(error)),
    }
}

/// The keys of `path` up to the first that serde could not name, as `spheres[2].radius`;
/// empty for none. A manifest that ends, or breaks, where a key should be leaves an
/// unnamed last key, which serde_path_to_error prints as `?` (`image.?`).
fn known_keys(path: &serde_path_to_error::Path) -> String {
    use serde_path_to_error::Segment;
    let mut keys = String::new();
    for segment in path.iter() {
        match segment {
            Segment::Unknown => break,
            Segment::Seq { index } => keys.push_str(&format!("[{index}]")),
            Segment::Map { key } | Segment::Enum { variant: key } => {
                if !keys.is_empty() {
                    keys.push('.');
                }
                keys.push_str(key);
            }
        }
    }
    keys
}

fn json_error(key: String, error: serde_json::Error) -> ManifestError {
    // serde_json appends " at line L column C" to its messages; the place is printed apart.
    let message = error.to_string();
    let suffix = format!(" at line {} column {}", error.line(), error.column());
    let message = message.strip_suffix(&suffix).unwrap_or(&message);
    // A key within a `raw::Tagged` object, which names only the object, comes first.
    let (key, message) = match message
        .strip_prefix(raw::NESTED)
        .and_then(|rest| rest.split_once(raw::NESTED))
    {
        Some((inner, message)) if inner.starts_with('[') => (format!("{key}{inner}"), message),
        Some((inner, message)) => (format!("{key}.{inner}"), message),
        None => (key, message),
    };
    ManifestError::Json {
        line: error.line(),
        column: error.column(),
        key: (!key.is_empty()).then_some(key),
        message: message.to_string(),
    }
}

/// The manifest exactly as written: serde shapes, no defaults applied, no rules checked.
mod raw {
    use std::collections::BTreeMap;
    use std::marker::PhantomData;

    use serde::Deserialize;
    use serde::de::value::MapAccessDeserializer;
    use serde::de::{self, Deserializer, IgnoredAny, MapAccess, SeqAccess, Visitor};

    use super::{Encoding, PpmStyle};

    pub type Vec3 = Numbers<3>;

    /// `N` numbers, from an array of exactly `N`. (serde's `[f64; N]` takes a longer array
    /// for trailing text, and says "trailing characters", which names no cause.)
    #[derive(Clone, Copy)]
    pub struct Numbers<const N: usize>(pub [f64; N]);

    impl<'de, const N: usize> Deserialize<'de> for Numbers<N> {
        fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
            struct NumbersVisitor<const N: usize>;
            impl<'de, const N: usize> Visitor<'de> for NumbersVisitor<N> {
                type Value = Numbers<N>;
                fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                    write!(f, "an array of {N} numbers")
                }
                fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Numbers<N>, A::Error> {
                    let mut numbers = [0.0; N];
                    for (i, x) in numbers.iter_mut().enumerate() {
                        *x = (seq.next_element()?)
                            .ok_or_else(|| de::Error::invalid_length(i, &self))?;
                    }
                    // The rest counted, to say how long the array is.
                    let mut len = N;
                    while seq.next_element::<IgnoredAny>()?.is_some() {
                        len += 1;
                    }
                    if len > N {
                        return Err(de::Error::invalid_length(len, &self));
                    }
                    Ok(Numbers(numbers))
                }
            }
            deserializer.deserialize_seq(NumbersVisitor::<N>)
        }
    }

    /// A `T` read from a JSON object, and only from one: serde's derived structs also take
    /// an array of their fields in order, so that `"image": [640, 480]` would pass
    /// unnoticed.
    pub struct Object<T>(pub T);

    impl<'de, T: Deserialize<'de>> Deserialize<'de> for Object<T> {
        fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
            struct ObjectVisitor<T>(PhantomData<T>);
            impl<'de, T: Deserialize<'de>> Visitor<'de> for ObjectVisitor<T> {
                type Value = T;
                fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                    f.write_str("a JSON object")
                }
                fn visit_map<A: MapAccess<'de>>(self, map: A) -> Result<T, A::Error> {
                    T::deserialize(MapAccessDeserializer::new(map))
                }
            }
            let object = deserializer.deserialize_map(ObjectVisitor(PhantomData))?;
            Ok(Object(object))
        }
    }

    /// An object that names its variant of `E` under `"type"` (`{"type": "stratified",
    /// "spp": 16}`), read as the externally tagged `E` (`{"stratified": {"spp": 16}}`).
    /// serde's internally tagged enums read such an object into a buffer first, and an
    /// error in a field then names only the object; here the fields are read again by a
    /// deserializer that tracks them, and an error names its key within the object (the
    /// message starts with [`NESTED`], the key, [`NESTED`] again: see `json_error`).
    pub struct Tagged<E>(pub E);

    /// Brackets the key within a [`Tagged`] object at the start of an error message.
    pub const NESTED: char = '\u{1f}';

    impl<'de, E: serde::de::DeserializeOwned> Deserialize<'de> for Tagged<E> {
        fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
            struct TaggedVisitor<E>(PhantomData<E>);
            impl<'de, E: serde::de::DeserializeOwned> Visitor<'de> for TaggedVisitor<E> {
                type Value = Tagged<E>;
                fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                    f.write_str("a JSON object")
                }
                fn visit_map<A: MapAccess<'de>>(self, mut map: A) -> Result<Tagged<E>, A::Error> {
                    let nested = |key: &str, message: &dyn std::fmt::Display| {
                        de::Error::custom(format_args!("{NESTED}{key}{NESTED}{message}"))
                    };
                    let mut fields = serde_json::Map::new();
                    while let Some((key, value)) = map.next_entry::<String, serde_json::Value>()? {
                        if fields.contains_key(&key) {
                            return Err(de::Error::custom(format_args!("duplicate field `{key}`")));
                        }
                        fields.insert(key, value);
                    }
                    let variant = match fields.remove("type") {
                        Some(serde_json::Value::String(variant)) => variant,
                        Some(other) => {
                            return Err(nested(
                                "type",
                                &format_args!("expected a string, got {other}"),
                            ));
                        }
                        None => return Err(de::Error::missing_field("type")),
                    };
                    let external = serde_json::Value::Object(serde_json::Map::from_iter([(
                        variant,
                        serde_json::Value::Object(fields),
                    )]));
                    match serde_path_to_error::deserialize::<_, E>(external) {
                        Ok(e) => Ok(Tagged(e)),
                        // The path starts at the variant, which is `type`'s value: none
                        // for an unknown variant, only the variant for a missing field.
                        Err(error) => match error.path().to_string() {
                            path if path == "." => Err(nested("type", error.inner())),
                            path => match path.split_once('.') {
                                Some((_, key)) => Err(nested(key, error.inner())),
                                None => Err(de::Error::custom(error.inner())),
                            },
                        },
                    }
                }
            }
            deserializer.deserialize_map(TaggedVisitor(PhantomData))
        }
    }

    /// `#[serde(deserialize_with)]` readers of fields that hold objects (see [`Object`]).
    fn object<'de, D: Deserializer<'de>, T: Deserialize<'de>>(d: D) -> Result<T, D::Error> {
        Object::deserialize(d).map(|Object(x)| x)
    }

    fn optional_object<'de, D: Deserializer<'de>, T: Deserialize<'de>>(
        d: D,
    ) -> Result<Option<T>, D::Error> {
        Ok(Option::<Object<T>>::deserialize(d)?.map(|Object(x)| x))
    }

    fn objects<'de, D: Deserializer<'de>, T: Deserialize<'de>>(
        d: D,
    ) -> Result<Option<Vec<T>>, D::Error> {
        let list = Option::<Vec<Object<T>>>::deserialize(d)?;
        Ok(list.map(|list| list.into_iter().map(|Object(x)| x).collect()))
    }

    fn named_objects<'de, D: Deserializer<'de>, T: Deserialize<'de>>(
        d: D,
    ) -> Result<Option<BTreeMap<String, T>>, D::Error> {
        let named = Option::<BTreeMap<String, Object<T>>>::deserialize(d)?;
        Ok(named.map(|named| named.into_iter().map(|(k, Object(x))| (k, x)).collect()))
    }

    #[derive(Deserialize)]
    #[serde(deny_unknown_fields)]
    pub struct Manifest {
        pub version: Option<i64>,
        #[serde(deserialize_with = "object")]
        pub image: Image,
        pub output: Option<String>,
        pub ppm: Option<PpmStyle>,
        pub encoding: Option<Encoding>,
        #[serde(default, deserialize_with = "optional_object")]
        pub camera: Option<Camera>,
        pub tmin: Option<f64>,
        pub tmax: Option<f64>,
        pub background: Option<Vec3>,
        #[serde(default, deserialize_with = "optional_object")]
        pub integrator: Option<Tagged<Integrator>>,
        #[serde(default, deserialize_with = "optional_object")]
        pub sampler: Option<Tagged<Sampler>>,
        #[serde(default, deserialize_with = "named_objects")]
        pub materials: Option<BTreeMap<String, Tagged<Material>>>,
        #[serde(default, deserialize_with = "objects")]
        pub spheres: Option<Vec<Sphere>>,
        #[serde(default, deserialize_with = "objects")]
        pub planes: Option<Vec<Plane>>,
        #[serde(default, deserialize_with = "objects")]
        pub meshes: Option<Vec<Mesh>>,
        #[serde(default, deserialize_with = "objects")]
        pub lights: Option<Vec<Tagged<Light>>>,
    }

    #[derive(Deserialize)]
    #[serde(deny_unknown_fields)]
    pub struct Image {
        pub width: u32,
        pub height: u32,
    }

    #[derive(Deserialize, Default)]
    #[serde(deny_unknown_fields)]
    pub struct Camera {
        pub origin: Option<Vec3>,
        pub right: Option<Vec3>,
        pub up: Option<Vec3>,
        pub forward: Option<Vec3>,
        pub look_from: Option<Vec3>,
        pub look_at: Option<Vec3>,
        pub vfov: Option<f64>,
        pub aperture: Option<f64>,
        pub focus_distance: Option<f64>,
    }

    #[derive(Deserialize)]
    #[serde(rename_all = "lowercase", deny_unknown_fields)]
    pub enum Integrator {
        Hit {},
        Depth { scale: Option<f64> },
        Normal {},
        Direct {},
        Whitted { max_depth: Option<i64> },
        Path { max_depth: Option<i64> },
    }

    #[derive(Deserialize)]
    #[serde(rename_all = "lowercase", deny_unknown_fields)]
    pub enum Sampler {
        Center { spp: Option<u32>, seed: Option<u64> },
        Independent { spp: Option<u32>, seed: Option<u64> },
        Stratified { spp: Option<u32>, seed: Option<u64> },
    }

    #[derive(Deserialize)]
    #[serde(rename_all = "lowercase", deny_unknown_fields)]
    pub enum Material {
        Diffuse {
            albedo: Vec3,
            emission: Option<Vec3>,
        },
        Mirror {
            reflectance: Vec3,
            emission: Option<Vec3>,
        },
        Dielectric {
            ior: f64,
            emission: Option<Vec3>,
        },
    }

    #[derive(Deserialize)]
    #[serde(deny_unknown_fields)]
    pub struct Sphere {
        pub center: Vec3,
        pub radius: f64,
        pub material: Option<String>,
    }

    #[derive(Deserialize)]
    #[serde(deny_unknown_fields)]
    pub struct Plane {
        pub point: Vec3,
        pub normal: Vec3,
        pub material: Option<String>,
    }

    #[derive(Deserialize)]
    #[serde(deny_unknown_fields)]
    pub struct Mesh {
        pub file: String,
        #[serde(default, deserialize_with = "optional_object")]
        pub transform: Option<Transform>,
        pub material: Option<String>,
    }

    #[derive(Deserialize)]
    #[serde(deny_unknown_fields)]
    pub struct Transform {
        pub matrix: Option<Numbers<16>>,
        /// A number or three numbers; checked by hand for a clear message.
        pub scale: Option<serde_json::Value>,
        #[serde(default, deserialize_with = "optional_object")]
        pub rotate: Option<Rotate>,
        pub translate: Option<Vec3>,
    }

    #[derive(Deserialize)]
    #[serde(deny_unknown_fields)]
    pub struct Rotate {
        pub axis: Vec3,
        pub degrees: f64,
    }

    #[derive(Deserialize)]
    #[serde(rename_all = "lowercase", deny_unknown_fields)]
    pub enum Light {
        Point { position: Vec3, intensity: Vec3 },
        Directional { direction: Vec3, irradiance: Vec3 },
    }
}

type Result<T> = std::result::Result<T, ManifestError>;

fn validate(raw: raw::Manifest, path: &Path) -> Result<Manifest> {
    let folder = path.parent().unwrap_or(Path::new(""));

    let version = raw.version.unwrap_or(1);
    if version != 1 {
        return Err(ManifestError::invalid(
            "version",
            format!("unsupported version {version} (this renderer reads version 1)"),
        ));
    }

    let (width, height) = (raw.image.width, raw.image.height);
    for (key, side) in [("image.width", width), ("image.height", height)] {
        if side == 0 || side > MAX_IMAGE_SIDE {
            return Err(ManifestError::invalid(
                key,
                format!("must be between 1 and {MAX_IMAGE_SIDE}, got {side}"),
            ));
        }
    }
    if u64::from(width) * u64::from(height) > MAX_PIXELS {
        return Err(ManifestError::invalid(
            "image",
            format!("{width} x {height} pixels is more than the limit of {MAX_PIXELS}"),
        ));
    }

    let (output, format) = output_path(raw.output.as_deref(), raw.ppm, path, folder)?;
    let encoding = raw.encoding.unwrap_or(Encoding::Linear);
    let camera = camera_desc(raw.camera.unwrap_or_default())?;

    let tmin = match raw.tmin {
        Some(t) => finite_at_least("tmin", t, 0.0)?,
        None => 0.0,
    };
    let tmax = match raw.tmax {
        Some(t) => finite("tmax", t)?,
        None => f64::INFINITY,
    };
    if tmax <= tmin {
        return Err(ManifestError::invalid(
            "tmax",
            format!(
                "must be greater than tmin ({}), got {}",
                shown(tmin),
                shown(tmax)
            ),
        ));
    }

    let background = match raw.background {
        Some(c) => colour("background", c)?,
        None => [0.0; 3],
    };
    let integrator = integrator_desc(raw.integrator.map(|raw::Tagged(i)| i))?;
    let sampler = sampler_desc(raw.sampler.map(|raw::Tagged(s)| s))?;

    let (materials, material_ids) = materials(raw.materials.unwrap_or_default())?;
    let material = |key: &dyn Key, name: Option<String>| -> Result<Option<MaterialId>> {
        match name {
            None => Ok(None),
            Some(name) => match material_ids.get(name.as_str()) {
                Some(&id) => Ok(Some(id)),
                None => Err(ManifestError::invalid(
                    key.spell(),
                    format!("unknown material `{name}`{}", known_names(&material_ids)),
                )),
            },
        }
    };

    let mut spheres = Vec::new();
    for (i, s) in raw.spheres.unwrap_or_default().into_iter().enumerate() {
        let key = |field: &'static str| move || format!("spheres[{i}].{field}");
        let center = point(&key("center"), s.center)?;
        let radius = finite(&key("radius"), s.radius)?;
        if !(radius > 0.0 && radius <= MAX_MAGNITUDE) {
            return Err(ManifestError::invalid(
                key("radius").spell(),
                format!(
                    "must be greater than 0 (and at most {MAX_MAGNITUDE:e}), got {}",
                    shown(radius)
                ),
            ));
        }
        let material = material(&key("material"), s.material)?;
        spheres.push(SphereDesc {
            center,
            radius,
            material,
        });
    }

    let mut planes = Vec::new();
    for (i, p) in raw.planes.unwrap_or_default().into_iter().enumerate() {
        let key = |field: &'static str| move || format!("planes[{i}].{field}");
        let point_ = point(&key("point"), p.point)?;
        let normal = direction(&key("normal"), p.normal)?;
        let material = material(&key("material"), p.material)?;
        planes.push(PlaneDesc {
            point: point_,
            normal,
            material,
        });
    }

    let mut meshes = Vec::new();
    for (i, m) in raw.meshes.unwrap_or_default().into_iter().enumerate() {
        let key = |field: &str| format!("meshes[{i}].{field}");
        if m.file.is_empty() {
            return Err(ManifestError::invalid(key("file"), "must not be empty"));
        }
        let file = folder.join(&m.file);
        if crate::mesh::MeshFormat::from_path(&file).is_none() {
            return Err(ManifestError::invalid(
                key("file"),
                format!(
                    "`{}`: unsupported mesh format (expected .obj, .gltf or .glb)",
                    m.file
                ),
            ));
        }
        let transform = match m.transform {
            Some(t) => transform_matrix(&key("transform"), t)?,
            None => DMat4::IDENTITY,
        };
        let material = material(&key("material"), m.material)?;
        meshes.push(MeshDesc {
            file,
            transform,
            material,
        });
    }

    let mut lights = Vec::new();
    for (i, raw::Tagged(l)) in raw.lights.unwrap_or_default().into_iter().enumerate() {
        let key = |field: &str| format!("lights[{i}].{field}");
        lights.push(match l {
            raw::Light::Point {
                position,
                intensity,
            } => Light::Point {
                position: point(&key("position"), position)?,
                intensity: colour(&key("intensity"), intensity)?,
            },
            raw::Light::Directional {
                direction: d,
                irradiance,
            } => Light::Directional {
                direction: direction(&key("direction"), d)?,
                irradiance: colour(&key("irradiance"), irradiance)?,
            },
        });
    }

    Ok(Manifest {
        source: path.to_path_buf(),
        width,
        height,
        output,
        format,
        encoding,
        camera,
        tmin,
        tmax,
        background,
        integrator,
        sampler,
        materials,
        spheres,
        planes,
        meshes,
        lights,
    })
}

fn known_names(ids: &HashMap<String, MaterialId>) -> String {
    if ids.is_empty() {
        return " (no materials are defined)".to_string();
    }
    let mut names: Vec<&str> = ids.keys().map(String::as_str).collect();
    names.sort_unstable();
    format!(" (defined: {})", names.join(", "))
}

fn output_path(
    output: Option<&str>,
    ppm: Option<PpmStyle>,
    manifest: &Path,
    folder: &Path,
) -> Result<(PathBuf, OutputFormat)> {
    let relative = match output {
        Some("") => return Err(ManifestError::invalid("output", "must not be empty")),
        Some(output) => PathBuf::from(output),
        None => {
            let stem = manifest.file_stem().unwrap_or_default();
            let mut name = stem.to_os_string();
            name.push(".ppm");
            PathBuf::from(name)
        }
    };
    if relative.file_name().is_none() {
        return Err(ManifestError::invalid(
            "output",
            format!("`{}` does not name a file", relative.display()),
        ));
    }
    let extension = relative
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase);
    let format = match extension.as_deref() {
        Some("ppm") => OutputFormat::Ppm(ppm.unwrap_or(PpmStyle::Plain)),
        Some("pfm") => OutputFormat::Pfm,
        _ => {
            return Err(ManifestError::invalid(
                "output",
                format!(
                    "`{}`: unsupported image format (expected a .ppm or .pfm extension)",
                    relative.display()
                ),
            ));
        }
    };
    Ok((folder.join(relative), format))
}

fn camera_desc(c: raw::Camera) -> Result<CameraDesc> {
    let look_at_form = c.look_from.is_some() || c.look_at.is_some();
    let frame = if look_at_form {
        for (key, present) in [
            ("origin", c.origin.is_some()),
            ("right", c.right.is_some()),
            ("forward", c.forward.is_some()),
        ] {
            if present {
                return Err(ManifestError::invalid(
                    format!("camera.{key}"),
                    "belongs to the basis camera; a camera with look_from/look_at cannot have it",
                ));
            }
        }
        let missing = |key: &str| {
            ManifestError::invalid(
                format!("camera.{key}"),
                "is required when the camera uses look_from/look_at",
            )
        };
        let from = point(
            "camera.look_from",
            c.look_from.ok_or_else(|| missing("look_from"))?,
        )?;
        let at = point(
            "camera.look_at",
            c.look_at.ok_or_else(|| missing("look_at"))?,
        )?;
        let up = match c.up {
            Some(up) => direction("camera.up", up)?,
            None => DVec3::Y,
        };
        let vfov = match c.vfov {
            Some(v) => finite("camera.vfov", v)?,
            None => 90.0,
        };
        if !(vfov > 0.0 && vfov < 180.0) {
            return Err(ManifestError::invalid(
                "camera.vfov",
                format!(
                    "must lie strictly between 0 and 180 degrees, got {}",
                    shown(vfov)
                ),
            ));
        }
        if from == at {
            return Err(ManifestError::invalid(
                "camera.look_at",
                "must differ from look_from",
            ));
        }
        camera::look_at_frame(from, at, up, vfov).ok_or_else(|| {
            ManifestError::invalid("camera.up", "must not be parallel to the view direction")
        })?
    } else {
        if c.vfov.is_some() {
            return Err(ManifestError::invalid(
                "camera.vfov",
                "belongs to the look-at camera (look_from/look_at); the basis camera zooms by the lengths of right, up and forward",
            ));
        }
        let vector = |key: &str, v: Option<raw::Vec3>, default: DVec3| match v {
            Some(v) => point(&format!("camera.{key}"), v),
            None => Ok(default),
        };
        let frame = CameraFrame {
            origin: vector("origin", c.origin, DVec3::ZERO)?,
            right: vector("right", c.right, DVec3::X)?,
            up: vector("up", c.up, DVec3::Y)?,
            forward: vector("forward", c.forward, DVec3::Z)?,
        };
        if frame.right.cross(frame.up).dot(frame.forward) == 0.0 {
            return Err(ManifestError::invalid(
                "camera",
                "right, up and forward must be linearly independent (some pixel would have no direction)",
            ));
        }
        frame
    };

    // Bounded as coordinates are: the lens moves ray origins by up to its radius.
    let aperture = match c.aperture {
        Some(a) => bounded(
            "camera.aperture",
            finite_at_least("camera.aperture", a, 0.0)?,
        )?,
        None => 0.0,
    };
    let focus_distance = match c.focus_distance {
        Some(f) => {
            let f = bounded("camera.focus_distance", f)?;
            if f <= 0.0 {
                return Err(ManifestError::invalid(
                    "camera.focus_distance",
                    format!("must be greater than 0, got {}", shown(f)),
                ));
            }
            Some(f)
        }
        None => None,
    };
    let lens = if aperture > 0.0 {
        let focus_distance = focus_distance.ok_or_else(|| {
            ManifestError::invalid(
                "camera.focus_distance",
                "is required when camera.aperture is greater than 0",
            )
        })?;
        Some(ThinLens {
            radius: aperture,
            focus_distance,
        })
    } else {
        None
    };
    Ok(CameraDesc { frame, lens })
}

fn integrator_desc(raw: Option<raw::Integrator>) -> Result<IntegratorDesc> {
    Ok(match raw {
        None | Some(raw::Integrator::Hit {}) => IntegratorDesc::Hit,
        Some(raw::Integrator::Depth { scale }) => {
            let scale = match scale {
                Some(s) => finite("integrator.scale", s)?,
                None => 1.0,
            };
            if scale <= 0.0 {
                return Err(ManifestError::invalid(
                    "integrator.scale",
                    format!("must be greater than 0, got {}", shown(scale)),
                ));
            }
            IntegratorDesc::Depth { scale }
        }
        Some(raw::Integrator::Normal {}) => IntegratorDesc::Normal,
        Some(raw::Integrator::Direct {}) => IntegratorDesc::Direct,
        Some(raw::Integrator::Whitted { max_depth }) => {
            let max_depth = match max_depth {
                Some(d) => u32::try_from(d).map_err(|_| {
                    ManifestError::invalid(
                        "integrator.max_depth",
                        format!("must be 0 or more, got {d}"),
                    )
                })?,
                None => 8,
            };
            IntegratorDesc::Whitted { max_depth }
        }
        Some(raw::Integrator::Path { max_depth }) => {
            let max_depth = match max_depth {
                None | Some(-1) => None,
                Some(d) => Some(u32::try_from(d).map_err(|_| {
                    ManifestError::invalid(
                        "integrator.max_depth",
                        format!("must be -1 (unbounded) or 0 or more, got {d}"),
                    )
                })?),
            };
            IntegratorDesc::Path { max_depth }
        }
    })
}

fn sampler_desc(raw: Option<raw::Sampler>) -> Result<SamplerDesc> {
    let (kind, spp, seed) = match raw {
        None => (SamplerKind::Center, None, None),
        Some(raw::Sampler::Center { spp, seed }) => (SamplerKind::Center, spp, seed),
        Some(raw::Sampler::Independent { spp, seed }) => (SamplerKind::Independent, spp, seed),
        Some(raw::Sampler::Stratified { spp, seed }) => (SamplerKind::Stratified, spp, seed),
    };
    let spp = spp.unwrap_or(1);
    if kind == SamplerKind::Center && spp != 1 {
        return Err(ManifestError::invalid(
            "sampler.spp",
            format!(
                "the center sampler takes exactly 1 sample per pixel, got {spp} (use \"independent\" or \"stratified\" for more)"
            ),
        ));
    }
    if spp == 0 || spp > MAX_SPP {
        return Err(ManifestError::invalid(
            "sampler.spp",
            format!("must be between 1 and {MAX_SPP}, got {spp}"),
        ));
    }
    Ok(SamplerDesc {
        kind,
        spp,
        seed: seed.unwrap_or(0),
    })
}

fn materials(
    raw: BTreeMap<String, raw::Tagged<raw::Material>>,
) -> Result<(Vec<Material>, HashMap<String, MaterialId>)> {
    let mut materials = Vec::with_capacity(raw.len());
    for (name, raw::Tagged(m)) in raw {
        let key = |field: &str| format!("materials.{name}.{field}");
        let (kind, emission) = match m {
            raw::Material::Diffuse { albedo, emission } => (
                MaterialKind::Diffuse {
                    albedo: unit_colour(&key("albedo"), albedo)?,
                },
                emission,
            ),
            raw::Material::Mirror {
                reflectance,
                emission,
            } => (
                MaterialKind::Mirror {
                    reflectance: unit_colour(&key("reflectance"), reflectance)?,
                },
                emission,
            ),
            raw::Material::Dielectric { ior, emission } => {
                let ior = finite(&key("ior"), ior)?;
                if !(ior > 0.0 && ior <= 100.0) {
                    return Err(ManifestError::invalid(
                        key("ior"),
                        format!(
                            "must be greater than 0 (and at most 100), got {}",
                            shown(ior)
                        ),
                    ));
                }
                (MaterialKind::Dielectric { ior }, emission)
            }
        };
        let emission = match emission {
            Some(e) => colour(&key("emission"), e)?,
            None => [0.0; 3],
        };
        materials.push(Material {
            name,
            kind,
            emission,
        });
    }
    let ids = materials
        .iter()
        .enumerate()
        .map(|(i, m)| (m.name.clone(), i))
        .collect();
    Ok((materials, ids))
}

fn transform_matrix(key: &str, t: raw::Transform) -> Result<DMat4> {
    let srt = t.scale.is_some() || t.rotate.is_some() || t.translate.is_some();
    if let Some(raw::Numbers(m)) = t.matrix {
        if srt {
            return Err(ManifestError::invalid(
                key,
                "give either `matrix` or any of `scale`, `rotate`, `translate`, not both",
            ));
        }
        for (i, &x) in m.iter().enumerate() {
            bounded(&format!("{key}.matrix[{i}]"), x)?;
        }
        if m[12..16] != [0.0, 0.0, 0.0, 1.0] {
            return Err(ManifestError::invalid(
                format!("{key}.matrix"),
                format!(
                    "the bottom row must be [0, 0, 0, 1], got [{}, {}, {}, {}]",
                    m[12], m[13], m[14], m[15]
                ),
            ));
        }
        return Ok(transform::from_row_major(&m));
    }
    let scale = match &t.scale {
        None => DVec3::ONE,
        Some(serde_json::Value::Number(n)) => {
            let s = n.as_f64().unwrap_or(f64::NAN);
            DVec3::splat(bounded(&format!("{key}.scale"), s)?)
        }
        Some(serde_json::Value::Array(items)) if items.len() == 3 => {
            let mut s = [0.0; 3];
            for (i, item) in items.iter().enumerate() {
                let item_key = format!("{key}.scale[{i}]");
                let x = item.as_f64().ok_or_else(|| {
                    ManifestError::invalid(&item_key, format!("expected a number, got {item}"))
                })?;
                s[i] = bounded(&item_key, x)?;
            }
            DVec3::from_array(s)
        }
        Some(other) => {
            return Err(ManifestError::invalid(
                format!("{key}.scale"),
                format!("expected a number or an array of three numbers, got {other}"),
            ));
        }
    };
    let rotation = match t.rotate {
        None => None,
        Some(r) => {
            let axis = direction(&format!("{key}.rotate.axis"), r.axis)?;
            let degrees = bounded(&format!("{key}.rotate.degrees"), r.degrees)?;
            Some((axis, degrees))
        }
    };
    let translate = match t.translate {
        Some(v) => point(&format!("{key}.translate"), v)?,
        None => DVec3::ZERO,
    };
    Ok(transform::scale_rotate_translate(
        scale, rotation, translate,
    ))
}

/// Where a value sits in the manifest (`spheres[3].radius`), spelled out only when an
/// error names it: a manifest may list a hundred thousand spheres, and formatting their
/// keys up front took as long as reading them. A key is text, or a closure making it.
trait Key {
    fn spell(&self) -> String;
}

impl Key for str {
    fn spell(&self) -> String {
        self.to_string()
    }
}

impl Key for String {
    fn spell(&self) -> String {
        self.clone()
    }
}

impl<F: Fn() -> String> Key for F {
    fn spell(&self) -> String {
        self()
    }
}

fn finite(key: &(impl Key + ?Sized), x: f64) -> Result<f64> {
    if x.is_finite() {
        Ok(x)
    } else {
        Err(ManifestError::invalid(
            key.spell(),
            format!("must be a finite number, got {x}"),
        ))
    }
}

fn finite_at_least(key: &(impl Key + ?Sized), x: f64, min: f64) -> Result<f64> {
    let x = finite(key, x)?;
    if x < min {
        return Err(ManifestError::invalid(
            key.spell(),
            format!("must be at least {}, got {}", shown(min), shown(x)),
        ));
    }
    Ok(x)
}

fn bounded(key: &(impl Key + ?Sized), x: f64) -> Result<f64> {
    let x = finite(key, x)?;
    if x.abs() > MAX_MAGNITUDE {
        return Err(ManifestError::invalid(
            key.spell(),
            format!(
                "{} is out of range (magnitudes up to {MAX_MAGNITUDE:e} are accepted)",
                shown(x)
            ),
        ));
    }
    Ok(x)
}

fn point(key: &(impl Key + ?Sized), raw::Numbers(v): raw::Vec3) -> Result<DVec3> {
    for (i, &x) in v.iter().enumerate() {
        bounded(&|| format!("{}[{i}]", key.spell()), x)?;
    }
    Ok(DVec3::from_array(v))
}

/// A direction: any non-zero vector, returned at unit length.
fn direction(key: &(impl Key + ?Sized), v: raw::Vec3) -> Result<DVec3> {
    let v = point(key, v)?;
    let length = v.length();
    if length == 0.0 {
        return Err(ManifestError::invalid(
            key.spell(),
            "must not be the zero vector",
        ));
    }
    Ok(v / length)
}

fn colour(key: &str, raw::Numbers(c): raw::Vec3) -> Result<Rgb> {
    for (i, &x) in c.iter().enumerate() {
        let x = bounded(&format!("{key}[{i}]"), x)?;
        if x < 0.0 {
            return Err(ManifestError::invalid(
                format!("{key}[{i}]"),
                format!("colours must not be negative, got {}", shown(x)),
            ));
        }
    }
    Ok(c)
}

/// A reflectance: each channel in [0, 1].
fn unit_colour(key: &str, c: raw::Vec3) -> Result<Rgb> {
    let c = colour(key, c)?;
    for (i, &x) in c.iter().enumerate() {
        if x > 1.0 {
            return Err(ManifestError::invalid(
                format!("{key}[{i}]"),
                format!("must lie in [0, 1], got {}", shown(x)),
            ));
        }
    }
    Ok(c)
}
