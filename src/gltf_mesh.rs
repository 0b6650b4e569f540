//! glTF 2.0 (`.gltf` and `.glb`) through the `gltf` crate's document model.
//!
//! The default scene is read (else scene 0, else every root node), every node recursively
//! with its transform composed from the root, and every triangle primitive (triangles,
//! strips and fans); points and lines are skipped with a warning. Buffers are read here
//! (GLB chunk, `data:` URIs, files beside the glTF) and accessors decoded here, with every
//! offset checked; images are never read or decoded. `POSITION` accessors missing the
//! bounds the format requires are read with a warning. A GLB's chunk is used where it lies
//! in the file's bytes and a large buffer file is mapped ([`FileBytes`]), not copied.

use std::borrow::Cow;
use std::collections::HashMap;
use std::ops::Deref;
use std::path::Path;

use base64::Engine;
use glam::{DMat4, DQuat, DVec3};
use gltf::accessor::{DataType, Dimensions};
use gltf::mesh::Mode;

use crate::error::{MeshError, Place};
use crate::file_bytes::FileBytes;
use crate::mesh::{Geometry, Instance, MeshFile};

pub fn parse(bytes: &[u8], path: &Path) -> Result<MeshFile, MeshError> {
    let fail = |place: Option<String>, message: String| MeshError::Gltf {
        path: path.to_path_buf(),
        place: Place(place),
        message,
    };
    let (document, blob, unbounded) = open(bytes).map_err(|(place, e)| fail(place, shorten(&e)))?;
    let buffers = load_buffers(&document, blob, path)
        .map_err(|(place, message)| fail(Some(place), message))?;
    let buffers: Vec<&[u8]> = buffers.iter().map(|b| &**b).collect();
    let document = &document;

    let roots: Vec<gltf::Node> = match document
        .default_scene()
        .or_else(|| document.scenes().next())
    {
        Some(scene) => scene.nodes().collect(),
        None => {
            let mut is_child = vec![false; document.nodes().len()];
            for node in document.nodes() {
                for child in node.children() {
                    is_child[child.index()] = true;
                }
            }
            document.nodes().filter(|n| !is_child[n.index()]).collect()
        }
    };

    let mut mesh = MeshFile::default();
    // One geometry per (mesh, primitive), shared by every node that instances it.
    let mut geometry_of: HashMap<(usize, usize), Option<usize>> = HashMap::new();
    let mut skipped: HashMap<&'static str, usize> = HashMap::new();
    let node_count = document.nodes().len();
    let mut pending: Vec<(gltf::Node, DMat4, usize)> = roots
        .into_iter()
        .rev()
        .map(|n| (n, DMat4::IDENTITY, 0))
        .collect();
    while let Some((node, parent, depth)) = pending.pop() {
        if depth > node_count {
            return Err(fail(
                Some(format!("nodes[{}]", node.index())),
                "the node hierarchy has a cycle".to_string(),
            ));
        }
        let transform = parent * node_matrix(&node);
        if let Some(node_mesh) = node.mesh() {
            for primitive in node_mesh.primitives() {
                let key = (node_mesh.index(), primitive.index());
                let place = || format!("meshes[{}].primitives[{}]", key.0, key.1);
                let geometry = match geometry_of.get(&key) {
                    Some(g) => *g,
                    None => {
                        let g = match primitive.mode() {
                            Mode::Triangles | Mode::TriangleStrip | Mode::TriangleFan => {
                                let geometry = read_primitive(&primitive, &buffers)
                                    .map_err(|(p, m)| fail(Some(p.unwrap_or_else(place)), m))?;
                                mesh.geometries.push(geometry);
                                Some(mesh.geometries.len() - 1)
                            }
                            Mode::Points => {
                                *skipped.entry("point").or_default() += 1;
                                None
                            }
                            Mode::Lines | Mode::LineLoop | Mode::LineStrip => {
                                *skipped.entry("line").or_default() += 1;
                                None
                            }
                        };
                        geometry_of.insert(key, g);
                        g
                    }
                };
                if let Some(geometry) = geometry {
                    mesh.instances.push(Instance {
                        geometry,
                        transform,
                    });
                }
            }
        }
        for child in node.children().collect::<Vec<_>>().into_iter().rev() {
            pending.push((child, transform, depth + 1));
        }
    }
    if !unbounded.is_empty() {
        let places: Vec<String> = unbounded
            .iter()
            .map(|a| format!("accessors[{a}]"))
            .collect();
        mesh.warnings.push(format!(
            "{}: {}: POSITION without min and max (glTF 2.0 requires them); read anyway",
            path.display(),
            places.join(", ")
        ));
    }
    let mut kinds: Vec<_> = skipped.into_iter().collect();
    kinds.sort();
    for (kind, count) in kinds {
        let plural = if count == 1 { "" } else { "s" };
        mesh.warnings.push(format!(
            "{}: skipped {count} {kind} primitive{plural} (only triangles are rendered)",
            path.display()
        ));
    }
    Ok(mesh)
}

/// Parses and validates a document. Required extensions that cannot change the geometry
/// (materials, textures, lights) are dropped before validation, and so is
/// `KHR_mesh_quantization`, whose integer positions [`read_accessor`] decodes; any other
/// required extension (Draco, meshopt, GPU instancing...) is refused by the validator.
///
/// A GLB's binary chunk is borrowed from `bytes`, not copied. The error's place is
/// `asset.version` when the file is of another glTF version ([`check_version`]). Also
/// returns the `POSITION` accessors that had no `min` or `max`
/// ([`accept_unbounded_positions`]).
fn open(bytes: &[u8]) -> Result<Opened<'_>, (Option<String>, String)> {
    let text = |e: gltf::Error| (None, e.to_string());
    if bytes.iter().all(u8::is_ascii_whitespace) {
        return Err((None, "the file is empty".to_string()));
    }
    let (json, blob) = if bytes.starts_with(b"glTF") {
        // `Glb::from_slice` subtracts the header's size from its length unchecked.
        const HEADER: u32 = 12;
        let word = |at: usize| {
            bytes
                .get(at..at + 4)
                .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        };
        if let Some(version) = word(4)
            && version != GLTF_MAJOR
        {
            return Err((
                None,
                format!(
                    "a GLB of container version {version} (glTF {version}): only glTF 2.0 is read"
                ),
            ));
        }
        if let Some(length) = word(8)
            && length < HEADER
        {
            return Err((
                None,
                format!(
                    "the GLB header gives the file's length {length}, less than the header's {HEADER} bytes"
                ),
            ));
        }
        let glb = gltf::binary::Glb::from_slice(bytes).map_err(text)?;
        (glb.json, glb.bin.map(BufferBytes::Chunk))
    } else {
        (Cow::Borrowed(bytes), None)
    };
    let mut root: gltf::json::Root = match gltf::json::deserialize::from_slice(&json) {
        Ok(root) => root,
        Err(e) => {
            // A glTF 1.0 file fails on its first map where 2.0 has an array; its version,
            // when it says one, is the more useful cause.
            let declared = serde_json::from_slice::<serde_json::Value>(&json)
                .ok()
                .and_then(|v| v.pointer("/asset/version").map(version_text));
            if let Some(version) = declared {
                check_version(&version)?;
            }
            return Err(text(gltf::Error::Deserialize(e)));
        }
    };
    check_version(&root.asset.version)?;
    root.extensions_required
        .retain(|name| !geometry_neutral(name));
    check_position_accessors(&root).map_err(|e| (None, e))?;
    let unbounded = accept_unbounded_positions(&mut root);
    Ok((
        gltf::Document::from_json(root).map_err(text)?,
        blob,
        unbounded,
    ))
}

/// What [`open`] gives: the document, a GLB's binary chunk, and the `POSITION` accessors
/// that had no bounds.
type Opened<'a> = (gltf::Document, Option<BufferBytes<'a>>, Vec<usize>);

/// Gives every `POSITION` accessor without a `min` or `max` a placeholder, so that the
/// validator, which refuses such files, reads them; returns those accessors' indices.
/// glTF 2.0 requires the bounds, but some exporters leave them out, and nothing here uses
/// them: boxes come from the vertices themselves. Bounds that are present are left to the
/// validator.
fn accept_unbounded_positions(root: &mut gltf::json::Root) -> Vec<usize> {
    let mut unbounded: Vec<usize> = position_accessors(root)
        .map(|(_, index)| index)
        .filter(|&index| {
            root.accessors
                .get(index)
                .is_some_and(|a| a.min.is_none() || a.max.is_none())
        })
        .collect();
    unbounded.sort_unstable();
    unbounded.dedup();
    for &index in &unbounded {
        let accessor = &mut root.accessors[index];
        for bound in [&mut accessor.min, &mut accessor.max] {
            bound.get_or_insert_with(|| serde_json::json!([0.0, 0.0, 0.0]));
        }
    }
    unbounded
}

/// The glTF major version read: 2 (`asset.version` "2.0", GLB container version 2).
const GLTF_MAJOR: u32 = 2;

/// Refuses an `asset.version` whose major version is a number other than
/// [`GLTF_MAJOR`]: glTF 1.0 lays out meshes, accessors and buffers differently, and the
/// specification asks readers to refuse a major version they do not know. A version
/// without a readable major number is left to the rest of the checks.
fn check_version(version: &str) -> Result<(), (Option<String>, String)> {
    let major = version
        .split('.')
        .next()
        .and_then(|m| m.trim().parse::<u32>().ok());
    match major {
        Some(major) if major != GLTF_MAJOR => Err((
            Some("asset.version".to_string()),
            format!("this is glTF {version}; only glTF 2.0 is read"),
        )),
        _ => Ok(()),
    }
}

/// `asset.version` as written: a string's text, or a number (some glTF 1.0 exporters
/// wrote `1`) as JSON prints it.
fn version_text(value: &serde_json::Value) -> String {
    match value {
        serde_json::Value::String(text) => text.clone(),
        other => other.to_string(),
    }
}

/// gltf-json's validation looks up each primitive's `POSITION` accessor before it checks
/// that the index exists (and panics when it does not), so it is checked here first.
fn check_position_accessors(root: &gltf::json::Root) -> Result<(), String> {
    match position_accessors(root).find(|&(_, index)| index >= root.accessors.len()) {
        Some(((m, p), index)) => Err(format!(
            "meshes[{m}].primitives[{p}].attributes.POSITION: accessor {index} does not exist (the file has {})",
            root.accessors.len()
        )),
        None => Ok(()),
    }
}

/// Every primitive's `POSITION` accessor index (not checked against the accessors), with
/// the primitive's `(mesh, primitive)` position.
fn position_accessors(
    root: &gltf::json::Root,
) -> impl Iterator<Item = ((usize, usize), usize)> + '_ {
    use gltf::json::mesh::Semantic;
    use gltf::json::validation::Checked;
    root.meshes.iter().enumerate().flat_map(|(m, mesh)| {
        mesh.primitives
            .iter()
            .enumerate()
            .filter_map(move |(p, primitive)| {
                let index = primitive
                    .attributes
                    .get(&Checked::Valid(Semantic::Positions))?;
                Some(((m, p), index.value()))
            })
    })
}

fn geometry_neutral(extension: &str) -> bool {
    ["KHR_materials_", "KHR_texture_", "EXT_texture_"]
        .iter()
        .any(|prefix| extension.starts_with(prefix))
        || [
            "KHR_mesh_quantization",
            "KHR_lights_punctual",
            "EXT_lights_image_based",
            "MSFT_texture_dds",
            "KHR_xmp_json_ld",
            "KHR_techniques_webgl",
            "KHR_technique_webgl",
        ]
        .contains(&extension)
}

/// The gltf crate lists every validation failure; a file missing one field per accessor
/// would print hundreds. Keep the first few.
fn shorten(message: &str) -> String {
    const KEEP: usize = 3;
    let parts: Vec<&str> = message.trim_end_matches(';').split("; ").collect();
    if parts.len() <= KEEP {
        return message.trim_end_matches(';').to_string();
    }
    format!(
        "{}; and {} more",
        parts[..KEEP].join("; "),
        parts.len() - KEEP
    )
}

/// The node's local transform in float64 (column-major matrix, or T·R·S).
fn node_matrix(node: &gltf::Node) -> DMat4 {
    match node.transform() {
        gltf::scene::Transform::Matrix { matrix } => {
            DMat4::from_cols_array_2d(&matrix.map(|c| c.map(f64::from)))
        }
        gltf::scene::Transform::Decomposed {
            translation,
            rotation,
            scale,
        } => {
            let [x, y, z, w] = rotation.map(f64::from);
            let rotation = DQuat::from_xyzw(x, y, z, w);
            // glTF requires unit quaternions; normalizing forgives rounding in the file.
            let rotation = if rotation.length() > 0.0 {
                rotation.normalize()
            } else {
                DQuat::IDENTITY
            };
            DMat4::from_scale_rotation_translation(
                DVec3::from_array(scale.map(f64::from)),
                rotation,
                DVec3::from_array(translation.map(f64::from)),
            )
        }
    }
}

type Fault = (Option<String>, String);

fn read_primitive(primitive: &gltf::Primitive, buffers: &[&[u8]]) -> Result<Geometry, Fault> {
    let positions = primitive
        .get(&gltf::Semantic::Positions)
        .ok_or((None, "has no POSITION attribute".to_string()))?;
    let at = |accessor: &gltf::Accessor| Some(format!("accessors[{}]", accessor.index()));
    if positions.dimensions() != Dimensions::Vec3 {
        return Err((at(&positions), "POSITION must be a VEC3".to_string()));
    }
    let plain = plain_elements(&positions, buffers, DataType::F32, f32::from_le_bytes);
    let positions_f32: Vec<[f32; 3]> = match plain {
        Some(read) => read.map_err(|m| (at(&positions), m))?,
        None => read_accessor(&positions, buffers)
            .map_err(|m| (at(&positions), m))?
            .chunks_exact(3)
            .map(|c| [c[0] as f32, c[1] as f32, c[2] as f32])
            .collect(),
    };

    let corners: Vec<u32> = match primitive.indices() {
        Some(indices) => {
            if indices.dimensions() != Dimensions::Scalar
                || !matches!(
                    indices.data_type(),
                    DataType::U8 | DataType::U16 | DataType::U32
                )
            {
                return Err((
                    at(&indices),
                    "indices must be unsigned integer scalars".to_string(),
                ));
            }
            let plain = plain_elements(&indices, buffers, DataType::U32, u32::from_le_bytes)
                .or_else(|| {
                    plain_elements(&indices, buffers, DataType::U16, |b| {
                        u32::from(u16::from_le_bytes(b))
                    })
                })
                .or_else(|| plain_elements(&indices, buffers, DataType::U8, |[b]| u32::from(b)));
            let corners: Vec<u32> = match plain {
                Some(read) => {
                    let read = read.map_err(|m| (at(&indices), m))?;
                    read.into_iter().map(|[i]| i).collect()
                }
                None => read_accessor(&indices, buffers)
                    .map_err(|m| (at(&indices), m))?
                    .into_iter()
                    // Exact: unsigned integers of at most 32 bits.
                    .map(|i| i as u32)
                    .collect(),
            };
            let n = positions_f32.len();
            if let Some(bad) = corners.iter().position(|&i| i as usize >= n) {
                return Err((
                    at(&indices),
                    format!("index {bad} is {}, past the {n} vertices", corners[bad]),
                ));
            }
            corners
        }
        None => (0..positions_f32.len() as u32).collect(),
    };

    let triangles = match primitive.mode() {
        Mode::TriangleStrip => (0..corners.len().saturating_sub(2))
            .map(|i| {
                // glTF 2.0, 3.7.2.1: p_i = {v_i, v_{i+(1+i%2)}, v_{i+(2-i%2)}}.
                let odd = i % 2;
                [corners[i], corners[i + 1 + odd], corners[i + 2 - odd]]
            })
            .collect(),
        Mode::TriangleFan => (0..corners.len().saturating_sub(2))
            .map(|i| [corners[i + 1], corners[i + 2], corners[0]])
            .collect(),
        _ => corners
            .chunks_exact(3)
            .map(|t| [t[0], t[1], t[2]])
            .collect(),
    };
    Ok(Geometry {
        positions: positions_f32,
        triangles,
    })
}

/// The elements of an accessor stored as plain values of `data_type` (`S` bytes each) with
/// no sparse substitutions (nearly every file's positions and indices), read straight from
/// the buffer, `N` components each, `read` decoding one component from its little-endian
/// bytes. `None` when the accessor needs [`read_accessor`]'s general path, which gives the
/// same values.
fn plain_elements<T, const N: usize, const S: usize>(
    accessor: &gltf::Accessor,
    buffers: &[&[u8]],
    data_type: DataType,
    read: impl Fn([u8; S]) -> T,
) -> Option<Result<Vec<[T; N]>, String>> {
    if accessor.data_type() != data_type
        || data_type.size() != S
        || accessor.normalized()
        || accessor.sparse().is_some()
        || accessor.dimensions().multiplicity() != N
    {
        return None;
    }
    let view = accessor.view()?;
    let count = accessor.count();
    let element = N * S;
    let stride = view.stride().unwrap_or(element);
    let bytes = match view_bytes(&view, accessor.offset(), count, element, stride, buffers) {
        Ok(bytes) => bytes,
        Err(message) => return Some(Err(message)),
    };
    // Fixed-size pieces let the compiler drop the bounds checks: this runs per vertex.
    let element_at = |chunk: &[u8]| {
        let (element, _) = chunk.split_at(element);
        std::array::from_fn(|c| read(element[c * S..(c + 1) * S].try_into().expect("S bytes")))
    };
    // `view_bytes` spans `count` elements, the last without its stride's padding.
    Some(Ok(bytes.chunks(stride).map(element_at).collect()))
}

/// Every component of every element of an accessor, in order, as f64 (exact for all glTF
/// component types). Sparse substitutions are applied; a missing buffer view means zeros.
fn read_accessor(accessor: &gltf::Accessor, buffers: &[&[u8]]) -> Result<Vec<f64>, String> {
    let components = accessor.dimensions().multiplicity();
    let data_type = accessor.data_type();
    let count = accessor.count();
    let normalized = accessor.normalized();
    let mut values = match accessor.view() {
        Some(view) => {
            let element = components * data_type.size();
            let stride = view.stride().unwrap_or(element);
            let bytes = view_bytes(&view, accessor.offset(), count, element, stride, buffers)?;
            let mut values = Vec::with_capacity(count * components);
            for i in 0..count {
                for c in 0..components {
                    let at = i * stride + c * data_type.size();
                    values.push(component(&bytes[at..], data_type, normalized));
                }
            }
            values
        }
        None => vec![0.0; count * components],
    };
    if let Some(sparse) = accessor.sparse() {
        let n = sparse.count();
        let index_type = match sparse.indices().index_type() {
            gltf::accessor::sparse::IndexType::U8 => DataType::U8,
            gltf::accessor::sparse::IndexType::U16 => DataType::U16,
            gltf::accessor::sparse::IndexType::U32 => DataType::U32,
        };
        let index_bytes = view_bytes(
            &sparse.indices().view(),
            sparse.indices().offset(),
            n,
            index_type.size(),
            index_type.size(),
            buffers,
        )
        .map_err(|m| format!("sparse indices: {m}"))?;
        let element = components * data_type.size();
        let value_bytes = view_bytes(
            &sparse.values().view(),
            sparse.values().offset(),
            n,
            element,
            element,
            buffers,
        )
        .map_err(|m| format!("sparse values: {m}"))?;
        for k in 0..n {
            let target =
                component(&index_bytes[k * index_type.size()..], index_type, false) as usize;
            if target >= count {
                return Err(format!(
                    "sparse index {target} is past the {count} elements"
                ));
            }
            for c in 0..components {
                values[target * components + c] = component(
                    &value_bytes[k * element + c * data_type.size()..],
                    data_type,
                    normalized,
                );
            }
        }
    }
    Ok(values)
}

/// The bytes of `count` elements of `element` bytes, `stride` apart, from `offset` within
/// `view`, after checking they lie inside both the view and its buffer.
fn view_bytes<'a>(
    view: &gltf::buffer::View,
    offset: usize,
    count: usize,
    element: usize,
    stride: usize,
    buffers: &[&'a [u8]],
) -> Result<&'a [u8], String> {
    if stride < element {
        return Err(format!(
            "byteStride {stride} is smaller than an element ({element} bytes)"
        ));
    }
    let buffer = buffers[view.buffer().index()];
    let span = if count == 0 {
        0
    } else {
        (count - 1)
            .checked_mul(stride)
            .and_then(|s| s.checked_add(element))
            .ok_or("the accessor's size overflows")?
    };
    let start = view
        .offset()
        .checked_add(offset)
        .ok_or("offset overflows")?;
    let end = start.checked_add(span).ok_or("offset overflows")?;
    if offset + span > view.length() || end > buffer.len() {
        return Err(format!(
            "{count} elements at offset {offset} reach past bufferView {} ({} bytes) or its buffer",
            view.index(),
            view.length()
        ));
    }
    Ok(&buffer[start..end])
}

fn component(bytes: &[u8], data_type: DataType, normalized: bool) -> f64 {
    let raw = match data_type {
        DataType::I8 => f64::from(bytes[0] as i8),
        DataType::U8 => f64::from(bytes[0]),
        DataType::I16 => f64::from(i16::from_le_bytes([bytes[0], bytes[1]])),
        DataType::U16 => f64::from(u16::from_le_bytes([bytes[0], bytes[1]])),
        DataType::U32 => f64::from(u32::from_le_bytes([bytes[0], bytes[1], bytes[2], bytes[3]])),
        DataType::F32 => f64::from(f32::from_le_bytes([bytes[0], bytes[1], bytes[2], bytes[3]])),
    };
    if !normalized {
        return raw;
    }
    // glTF 2.0, 3.11: normalized integers map to [0, 1] or [-1, 1].
    match data_type {
        DataType::I8 => (raw / 127.0).max(-1.0),
        DataType::U8 => raw / 255.0,
        DataType::I16 => (raw / 32767.0).max(-1.0),
        DataType::U16 => raw / 65535.0,
        _ => raw,
    }
}

/// Every buffer's bytes: the GLB binary chunk, a `data:` URI, or a file beside the glTF.
fn load_buffers<'a>(
    document: &gltf::Document,
    blob: Option<BufferBytes<'a>>,
    path: &Path,
) -> Result<Vec<BufferBytes<'a>>, (String, String)> {
    let folder = path.parent().unwrap_or(Path::new(""));
    let mut blob = blob;
    let mut buffers = Vec::new();
    for buffer in document.buffers() {
        let place = format!("buffers[{}]", buffer.index());
        let data = match buffer.source() {
            gltf::buffer::Source::Bin => blob.take().ok_or((
                place.clone(),
                "refers to a GLB binary chunk that is missing".to_string(),
            ))?,
            gltf::buffer::Source::Uri(uri) => {
                read_uri(uri, folder).map_err(|m| (place.clone(), m))?
            }
        };
        if data.len() < buffer.length() {
            return Err((
                place,
                format!(
                    "holds {} bytes but declares {}",
                    data.len(),
                    buffer.length()
                ),
            ));
        }
        buffers.push(data);
    }
    Ok(buffers)
}

/// A buffer's bytes: borrowed from the GLB file or decoded from a `data:` URI, or a file
/// of its own, mapped like mesh files ([`FileBytes`]).
enum BufferBytes<'a> {
    Chunk(Cow<'a, [u8]>),
    File(FileBytes),
}

impl Deref for BufferBytes<'_> {
    type Target = [u8];

    fn deref(&self) -> &[u8] {
        match self {
            BufferBytes::Chunk(bytes) => bytes,
            BufferBytes::File(bytes) => bytes,
        }
    }
}

fn read_uri(uri: &str, folder: &Path) -> Result<BufferBytes<'static>, String> {
    if let Some(rest) = uri.strip_prefix("data:") {
        let (_, payload) = rest
            .split_once(";base64,")
            .ok_or("only base64 data URIs are supported")?;
        return base64::engine::general_purpose::STANDARD
            .decode(payload)
            .map(|bytes| BufferBytes::Chunk(Cow::Owned(bytes)))
            .map_err(|e| format!("bad base64 data: {e}"));
    }
    if uri.contains("://") || uri.starts_with("file:") {
        return Err(format!(
            "unsupported URI `{uri}` (use a path relative to the glTF file)"
        ));
    }
    let relative = percent_decode(uri).ok_or_else(|| format!("malformed URI `{uri}`"))?;
    let file = folder.join(relative);
    FileBytes::open(&file)
        .map(BufferBytes::File)
        .map_err(|e| format!("cannot read {}: {e}", file.display()))
}

/// Decodes `%XX` escapes of a relative URI; `None` for a bad escape or invalid UTF-8.
fn percent_decode(uri: &str) -> Option<String> {
    let bytes = uri.as_bytes();
    let mut out = Vec::with_capacity(bytes.len());
    let mut i = 0;
    while i < bytes.len() {
        if bytes[i] == b'%' {
            let hex = std::str::from_utf8(bytes.get(i + 1..i + 3)?).ok()?;
            out.push(u8::from_str_radix(hex, 16).ok()?);
            i += 3;
        } else {
            out.push(bytes[i]);
            i += 1;
        }
    }
    String::from_utf8(out).ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn percent_escapes_decode_and_bad_ones_are_refused() {
        assert_eq!(percent_decode("a%20b.bin").as_deref(), Some("a b.bin"));
        assert_eq!(percent_decode("plain.bin").as_deref(), Some("plain.bin"));
        assert_eq!(percent_decode("bad%2"), None);
        assert_eq!(percent_decode("bad%zz"), None);
        assert_eq!(percent_decode("%ff"), None);
    }

    /// A one-primitive document: `positions` stored interleaved with a padding float (a
    /// 16-byte stride) after `lead` bytes, then `corners` as `index_type` (5121, 5123 or
    /// 5125).
    fn document(positions: &[[f32; 3]], corners: &[u32], index_type: u32, lead: usize) -> String {
        let mut buffer = vec![0xAB_u8; lead];
        for p in positions {
            for c in p.iter().chain(&[-7.0]) {
                buffer.extend_from_slice(&c.to_le_bytes());
            }
        }
        let index_offset = buffer.len();
        let (lo, hi) = positions.iter().fold(
            ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]),
            |(lo, hi), p| {
                (
                    [0, 1, 2].map(|k| lo[k].min(p[k])),
                    [0, 1, 2].map(|k| hi[k].max(p[k])),
                )
            },
        );
        for &i in corners {
            match index_type {
                5121 => buffer.push(i as u8),
                5123 => buffer.extend_from_slice(&(i as u16).to_le_bytes()),
                _ => buffer.extend_from_slice(&i.to_le_bytes()),
            }
        }
        serde_json::json!({
            "asset": {"version": "2.0"},
            "buffers": [{"byteLength": buffer.len(), "uri": format!(
                "data:application/octet-stream;base64,{}",
                base64::engine::general_purpose::STANDARD.encode(&buffer))}],
            "bufferViews": [
                {"buffer": 0, "byteOffset": lead, "byteLength": index_offset - lead,
                 "byteStride": 16},
                {"buffer": 0, "byteOffset": index_offset, "byteLength": buffer.len() - index_offset}
            ],
            "accessors": [
                {"bufferView": 0, "componentType": 5126, "count": positions.len(),
                 "type": "VEC3", "min": lo, "max": hi},
                {"bufferView": 1, "componentType": index_type, "count": corners.len(),
                 "type": "SCALAR"}
            ],
            "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}],
            "nodes": [{"mesh": 0}],
            "scenes": [{"nodes": [0]}]
        })
        .to_string()
    }

    #[test]
    fn positions_and_indices_of_every_index_type_and_a_stride_are_read_exactly() {
        let positions = [
            [0.1, -2.5, 3.0e-7],
            [f32::MAX, 1.0, -0.0],
            [7.25, f32::MIN_POSITIVE, 1.0e30],
            [-1.0, 0.5, 2.0],
        ];
        let corners = [0, 1, 2, 2, 3, 0];
        for index_type in [5121, 5123, 5125] {
            for lead in [0, 4, 12] {
                let text = document(&positions, &corners, index_type, lead);
                let mesh = parse(text.as_bytes(), Path::new("t.gltf"))
                    .unwrap_or_else(|e| panic!("{index_type} {lead}: {e}"));
                let geometry = &mesh.geometries[0];
                let bits =
                    |p: &[[f32; 3]]| p.iter().flatten().map(|c| c.to_bits()).collect::<Vec<_>>();
                assert_eq!(
                    bits(&geometry.positions),
                    bits(&positions),
                    "{index_type} {lead}"
                );
                assert_eq!(
                    geometry.triangles,
                    [[0, 1, 2], [2, 3, 0]],
                    "{index_type} {lead}"
                );
            }
        }
        // An index past the vertices names the accessor, the index's place and its value.
        let text = document(&positions, &[0, 1, 4], 5125, 0);
        let error = parse(text.as_bytes(), Path::new("t.gltf"))
            .unwrap_err()
            .to_string();
        assert!(
            error.contains("accessors[1]") && error.contains("index 2 is 4"),
            "{error}"
        );
    }

    #[test]
    fn normalized_components_follow_the_spec() {
        assert_eq!(component(&[127], DataType::I8, true), 1.0);
        assert_eq!(component(&[128], DataType::I8, true), -1.0);
        assert_eq!(component(&[255], DataType::U8, true), 1.0);
        assert_eq!(component(&[0xff, 0xff], DataType::U16, true), 1.0);
    }
}
