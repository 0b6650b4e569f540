//! Mutated inputs: every reader, and the renderer behind the manifest reader, refuses or
//! accepts them, and never panics. The seeds are the repository's scenes and models and a
//! hand-made GLB; the mutations are deterministic: bytes flipped, inserted, deleted and
//! repeated, 32-bit fields overwritten with edge values, and JSON values replaced.
//!
//! Mutations like these found the panics now refused with a place in `errors` and
//! `robustness`: a GLB header whose length is shorter than the header, an OBJ relative
//! index before the first texture coordinate, a glTF `POSITION` past the accessors, and
//! a `vfov` of 31e-300 degrees whose NaN camera rays overflowed the sphere tree's stack.

use std::panic::{AssertUnwindSafe, catch_unwind};
use std::path::Path;

use raybatch::Manifest;
use raybatch::job::{Batch, JobOptions};
use serde_json::{Value, json};

use crate::util::{Dir, repo};

/// Mutations per seed file.
const CASES_PER_SEED: usize = 400;
/// Manifests are rendered when their pixel samples are at most this many.
const MAX_RENDERED_SAMPLES: u64 = 4096;

struct XorShift(u64);

impl XorShift {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        self.0
    }

    fn below(&mut self, n: usize) -> usize {
        (self.next() % n.max(1) as u64) as usize
    }

    fn pick<'a, T>(&mut self, items: &'a [T]) -> &'a T {
        &items[self.below(items.len())]
    }
}

/// Text that readers treat specially: numbers at the edges of their types, separators,
/// keywords of OBJ and JSON.
const TOKENS: &[&str] = &[
    "-1",
    "0",
    "-0",
    "1e309",
    "nan",
    "inf",
    "4294967296",
    "-2147483648",
    "1e-320",
    " ",
    "\n",
    "/",
    "//",
    "f ",
    "v ",
    "vt ",
    "vn ",
    "o ",
    "\r\n",
    "\t",
    "#",
    "\\\n",
    "-1/-1/-1",
    "\"",
    ",",
    "[",
    "]",
    "{",
    "}",
    ":",
    "null",
    "[]",
    "\u{FEFF}",
    "\u{FF}",
    "\0",
];

/// 32-bit values for length, count and index fields.
const WORDS: &[u32] = &[0, 1, 4, 11, 12, 13, 0x7fff_ffff, 0xffff_ffff, 0x8000_0000];

fn mutate_bytes(random: &mut XorShift, seed: &[u8]) -> Vec<u8> {
    let mut out = seed.to_vec();
    for _ in 0..1 + random.below(4) {
        let at = random.below(out.len() + 1);
        let rest = out.len() - at;
        match random.below(6) {
            0 if at < out.len() => out[at] ^= 1 << random.below(8),
            1 | 2 => {
                let token = random.pick(TOKENS).as_bytes();
                out.splice(at..at, token.iter().copied());
            }
            3 if rest >= 4 => {
                let word = random.pick(WORDS).to_le_bytes();
                let at = at & !3;
                out[at..at + 4].copy_from_slice(&word);
            }
            4 => {
                out.drain(at..at + random.below(16).min(rest));
            }
            _ => {
                let piece = out[at..at + random.below(40).min(rest)].to_vec();
                let to = random.below(out.len() + 1);
                out.splice(to..to, piece);
            }
        }
    }
    out
}

/// Numbers for manifests' values.
const NUMBERS: &[f64] = &[
    0.0,
    -0.0,
    1.0,
    -1.0,
    0.5,
    1e-300,
    5e-324,
    1e15,
    1e16,
    -1e15,
    1e300,
    65536.0,
    65537.0,
    4294967296.0,
    180.0,
    179.9999999,
    1e-7,
    1048577.0,
    0.001,
];
/// Numbers for glTF's values: counts, offsets, strides, component types and targets.
const GLTF_NUMBERS: &[f64] = &[
    0.0,
    1.0,
    2.0,
    3.0,
    4.0,
    6.0,
    8.0,
    12.0,
    16.0,
    36.0,
    255.0,
    256.0,
    65535.0,
    4294967295.0,
    4294967296.0,
    -1.0,
    5120.0,
    5121.0,
    5122.0,
    5123.0,
    5125.0,
    5126.0,
    34962.0,
    34963.0,
    0.5,
    1e300,
];
const STRINGS: &[&str] = &[
    "",
    "hit",
    "depth",
    "normal",
    "path",
    "center",
    "independent",
    "stratified",
    "plain",
    "binary",
    "srgb",
    "linear",
    "pfm",
    "models/icosphere.obj",
    "models/stack.gltf",
    "models/seed.glb",
    "missing.obj",
    "../outside.ppm",
    "sub/out.ppm",
    "VEC2",
    "VEC3",
    "SCALAR",
    "MAT4",
    "POSITION",
    "data:application/octet-stream;base64,AAAA",
    "seed.bin",
];

/// `seed` with one or two of its JSON values (objects and arrays included) changed:
/// mostly for another of the same type (a number for a number, an array one item longer
/// or shorter), sometimes for another type.
fn mutate_json(random: &mut XorShift, seed: &Value, numbers: &[f64]) -> Value {
    let mut value = seed.clone();
    for _ in 0..1 + random.below(2) {
        let mut places = Vec::new();
        json_places(&value, String::new(), &mut places);
        let place = random.pick(&places).clone();
        let target = value.pointer_mut(&place).unwrap();
        let old = target.clone();
        let same_type = random.below(5) != 0;
        *target = match old {
            Value::Number(n) if same_type => match random.below(3) {
                0 => json!(n.as_f64().unwrap_or(0.0) * random.pick(numbers)),
                1 => json!(random.below(40)),
                _ => json!(random.pick(numbers)),
            },
            Value::String(_) if same_type => json!(random.pick(STRINGS)),
            Value::Array(mut items) if same_type => {
                if random.below(2) == 0 && !items.is_empty() {
                    items.pop();
                } else if let Some(item) = items.get(random.below(items.len())).cloned() {
                    items.push(item);
                }
                Value::Array(items)
            }
            Value::Object(mut map) if same_type => {
                let keys: Vec<String> = map.keys().cloned().collect();
                if !keys.is_empty() {
                    map.remove(random.pick(&keys));
                }
                Value::Object(map)
            }
            other => match random.below(5) {
                0 => json!(random.pick(numbers)),
                1 => json!(random.pick(STRINGS)),
                2 => Value::Null,
                3 => json!([other]),
                _ => json!(true),
            },
        };
    }
    value
}

/// JSON pointers to every value of `value`.
fn json_places(value: &Value, at: String, out: &mut Vec<String>) {
    match value {
        Value::Object(map) => {
            for (key, item) in map {
                json_places(item, format!("{at}/{key}"), out);
            }
        }
        Value::Array(items) => {
            for (i, item) in items.iter().enumerate() {
                json_places(item, format!("{at}/{i}"), out);
            }
        }
        _ => {}
    }
    out.push(at);
}

/// One triangle as glTF: the document and its binary buffer.
fn triangle_gltf() -> (Value, Vec<u8>) {
    let mut bin = Vec::new();
    for c in [0f32, 0.0, 3.0, 1.0, 0.0, 3.0, 0.0, 1.0, 3.0] {
        bin.extend_from_slice(&c.to_le_bytes());
    }
    for i in [0u16, 1, 2, 0] {
        bin.extend_from_slice(&i.to_le_bytes());
    }
    let document = json!({
        "asset": {"version": "2.0"},
        "buffers": [{"byteLength": bin.len()}],
        "bufferViews": [{"buffer": 0, "byteLength": 36, "byteStride": 12},
                        {"buffer": 0, "byteOffset": 36, "byteLength": 6}],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3",
             "min": [0, 0, 3], "max": [1, 1, 3]},
            {"bufferView": 1, "componentType": 5123, "count": 3, "type": "SCALAR"}
        ],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}],
        "nodes": [{"mesh": 0, "children": [1]}, {"mesh": 0, "translation": [1, 0, 0]}],
        "scenes": [{"nodes": [0]}]
    });
    (document, bin)
}

/// A GLB: header, JSON chunk, BIN chunk.
fn glb(document: &Value, bin: &[u8]) -> Vec<u8> {
    let mut text = document.to_string().into_bytes();
    while !text.len().is_multiple_of(4) {
        text.push(b' ');
    }
    let mut glb = b"glTF".to_vec();
    glb.extend_from_slice(&2u32.to_le_bytes());
    glb.extend_from_slice(&((12 + 8 + text.len() + 8 + bin.len()) as u32).to_le_bytes());
    glb.extend_from_slice(&(text.len() as u32).to_le_bytes());
    glb.extend_from_slice(b"JSON");
    glb.extend_from_slice(&text);
    glb.extend_from_slice(&(bin.len() as u32).to_le_bytes());
    glb.extend_from_slice(b"BIN\0");
    glb.extend_from_slice(bin);
    glb
}

fn seed_glb() -> Vec<u8> {
    let (document, bin) = triangle_gltf();
    glb(&document, &bin)
}

/// Runs `case` on each mutation, collecting the ones that panic (with what they were).
fn panics_of<T>(
    mutations: impl Iterator<Item = T>,
    describe: impl Fn(&T) -> String,
    mut case: impl FnMut(&T),
) -> Vec<String> {
    let mut failed = Vec::new();
    for mutation in mutations {
        if catch_unwind(AssertUnwindSafe(|| case(&mutation))).is_err() {
            failed.push(describe(&mutation));
        }
    }
    failed
}

/// Reads a mesh file's bytes as `raybatch` would (by its extension); for OBJ, checks that
/// the fast reader agrees with `tobj` on what reads.
fn read_mesh(name: &str, bytes: &[u8]) -> Result<(), String> {
    let path = Path::new(name);
    if name.ends_with(".obj") {
        let fast = raybatch::obj::parse(bytes, path);
        let reference = raybatch::obj::parse_with_tobj(bytes, path);
        assert_eq!(
            fast.as_ref().map(|m| m.triangle_count()).ok(),
            reference.as_ref().map(|m| m.triangle_count()).ok()
        );
        fast.map(|_| ()).map_err(|e| e.to_string())
    } else {
        raybatch::gltf_mesh::parse(bytes, path)
            .map(|_| ())
            .map_err(|e| e.to_string())
    }
}

#[test]
fn mutated_mesh_files_are_read_or_refused_without_a_panic() {
    let (document, bin) = triangle_gltf();
    let stack: Value =
        serde_json::from_slice(&std::fs::read(repo("models/stack.gltf")).unwrap()).unwrap();
    let mut random = XorShift(0x05ee_d0ff_11e5);
    let bytes = |seed: &[u8], random: &mut XorShift| -> Vec<Vec<u8>> {
        (0..CASES_PER_SEED)
            .map(|_| mutate_bytes(random, seed))
            .collect()
    };
    let values = |seed: &Value, random: &mut XorShift| -> Vec<Value> {
        (0..CASES_PER_SEED)
            .map(|_| mutate_json(random, seed, GLTF_NUMBERS))
            .collect()
    };
    // Per seed: its name, as read, and its mutations.
    type Seed = (&'static str, Vec<u8>, Vec<Vec<u8>>);
    let cases: Vec<Seed> = vec![
        {
            let obj = std::fs::read(repo("models/icosphere.obj")).unwrap();
            let mutations = bytes(&obj, &mut random);
            ("icosphere.obj", obj, mutations)
        },
        {
            let obj = b"o a\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvn 0 0 1\n\
                        f 1/1/1 2/2/1 3/1/1 4/2/1\ng b\nf -1 -2 -3\nf 1//1 2//1 4//1\nl 1 2\n"
                .to_vec();
            let mutations = bytes(&obj, &mut random);
            ("quads.obj", obj, mutations)
        },
        {
            let mutations = values(&stack, &mut random);
            let mutations = mutations.iter().map(|v| v.to_string().into_bytes());
            (
                "stack.gltf",
                stack.to_string().into_bytes(),
                mutations.collect(),
            )
        },
        {
            let mutations = values(&document, &mut random);
            let mutations = mutations.iter().map(|v| glb(v, &bin));
            ("values.glb", glb(&document, &bin), mutations.collect())
        },
        {
            let seed = glb(&document, &bin);
            let mutations = bytes(&seed, &mut random);
            ("bytes.glb", seed, mutations)
        },
    ];
    for (name, seed, mutations) in &cases {
        read_mesh(name, seed).unwrap_or_else(|e| panic!("seed {name}: {e}"));
        let failed = panics_of(
            mutations.iter(),
            |m| format!("{name}: {:?}", String::from_utf8_lossy(m)),
            |m| {
                let _ = read_mesh(name, m);
            },
        );
        assert!(
            failed.is_empty(),
            "{} panics, first: {}",
            failed.len(),
            failed[0]
        );
        // Enough mutations read for the readers past the first fault to be exercised too.
        let read = mutations
            .iter()
            .filter(|m| read_mesh(name, m).is_ok())
            .count();
        assert!(
            read >= CASES_PER_SEED / 100,
            "{name}: only {read} mutations read"
        );
    }
}

#[test]
fn mutated_manifests_are_rendered_or_refused_without_a_panic() {
    let dir = Dir::new();
    for model in [
        "icosphere.obj",
        "torus.obj",
        "pixel-grid.obj",
        "sliver-wedge.obj",
        "stack.gltf",
    ] {
        dir.write(
            &format!("models/{model}"),
            std::fs::read(repo(&format!("models/{model}"))).unwrap(),
        );
    }
    dir.write("models/seed.glb", seed_glb());
    // The repository's scenes, small, their meshes in `models/`.
    let mut seeds = Vec::new();
    for folder in ["scenes", "scenes/stress"] {
        for entry in std::fs::read_dir(repo(folder)).unwrap() {
            let path = entry.unwrap().path();
            if path.extension().is_none_or(|e| e != "json") {
                continue;
            }
            let mut scene: Value = serde_json::from_slice(&std::fs::read(&path).unwrap()).unwrap();
            scene["image"] = json!({"width": 24, "height": 16});
            for mesh in scene["meshes"].as_array_mut().into_iter().flatten() {
                let file = Path::new(mesh["file"].as_str().unwrap())
                    .file_name()
                    .unwrap();
                mesh["file"] = json!(format!("models/{}", file.to_str().unwrap()));
            }
            seeds.push(scene);
        }
    }
    seeds.push(json!({
        "image": {"width": 12, "height": 8}, "ppm": "plain", "encoding": "srgb",
        "camera": {"look_from": [0, 1, 5], "look_at": [0, 0, 0], "vfov": 50,
                   "aperture": 0.1, "focus_distance": 5},
        "integrator": {"type": "normal"},
        "sampler": {"type": "independent", "spp": 4, "seed": 7},
        "materials": {"red": {"type": "diffuse", "albedo": [0.8, 0.1, 0.1]}},
        "lights": [{"type": "point", "position": [0, 4, 0], "intensity": [10, 10, 10]}],
        "spheres": [{"center": [0, 0, 0], "radius": 1, "material": "red"}],
        "planes": [{"point": [0, -1, 0], "normal": [0, 1, 0]}],
        "meshes": [
            {"file": "models/seed.glb", "transform": {"scale": [0.5, 0.4, 0.5],
             "rotate": {"axis": [0, 1, 1], "degrees": 30}, "translate": [2, 0, 0]}},
            {"file": "models/stack.gltf", "transform": {"matrix":
             [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, -2, 0, 0, 0, 1]}}
        ]
    }));
    let mut random = XorShift(0x6a7_5eed);
    let manifest = dir.join("job.json");
    let (mut rendered, mut refused) = (0, 0);
    for (s, seed) in seeds.iter().enumerate() {
        let failed = panics_of(
            (0..CASES_PER_SEED).map(|_| mutate_json(&mut random, seed, NUMBERS)),
            |m| format!("seed {s}: {m}"),
            |m| {
                let text = m.to_string();
                let cheap = Manifest::parse(text.as_bytes(), &manifest).map(|m| {
                    u64::from(m.width) * u64::from(m.height) * u64::from(m.sampler.spp)
                        <= MAX_RENDERED_SAMPLES
                });
                match cheap {
                    Ok(true) => {
                        std::fs::write(&manifest, &text).unwrap();
                        // A batch of its own: one batch refuses to write an output twice.
                        let mut batch = Batch::new(JobOptions {
                            out_dir: Some(dir.join("out")),
                            ..JobOptions::default()
                        });
                        let report = batch.run(&manifest, &|_| {});
                        if report.ok() {
                            rendered += 1;
                        } else {
                            refused += 1;
                        }
                    }
                    Ok(false) => {}
                    Err(_) => refused += 1,
                }
            },
        );
        assert!(
            failed.is_empty(),
            "{} panics, first: {}",
            failed.len(),
            failed[0]
        );
    }
    let cases = seeds.len() * CASES_PER_SEED;
    assert!(
        rendered > cases / 4 && refused > cases / 10,
        "{rendered} rendered, {refused} refused of {cases}"
    );
}
