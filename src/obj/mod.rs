//! Wavefront OBJ: every object and group in file order, each polygon `v0 v1 … vn` split
//! into the fan `(v0, vi, vi+1)`. Points, lines and material libraries are not read.
//!
//! Two readers give the same [`MeshFile`], vertex for vertex: `tobj`, the reference, which
//! knows every corner of the format and whose faults we report by line; and [`fast`], a
//! parallel reader of the subset nearly every file uses, several times faster. The fast
//! reader declines anything outside its subset, and every fault, and `tobj` then reads
//! the file: what a file means and how a bad one is reported are always `tobj`'s.

pub mod fast;
mod tobj_reader;

use std::path::Path;

use crate::error::MeshError;
use crate::mesh::MeshFile;

/// Reads an OBJ file's bytes (`path` is for messages).
pub fn parse(bytes: &[u8], path: &Path) -> Result<MeshFile, MeshError> {
    match fast::parse(bytes) {
        Some(mesh) => Ok(mesh),
        None => parse_with_tobj(bytes, path),
    }
}

/// Reads an OBJ file's bytes with `tobj` only.
pub fn parse_with_tobj(bytes: &[u8], path: &Path) -> Result<MeshFile, MeshError> {
    tobj_reader::parse(bytes, path)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Random OBJ-like text: mostly valid lines, with every kind of fault and oddity the
    /// format allows (weights, colours, points, lines, relative and forward references,
    /// bad numbers, CRLF, tabs, UTF-8 comments, empty objects).
    fn random_obj(seed: u64) -> String {
        let mut random =
            crate::test_random::XorShift::new(seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1);
        let mut next = move |n: u64| random.below(n);
        let number = |r: u64| match r % 6 {
            0 => "0".to_string(),
            1 => format!("-{}.{}", r % 97, r % 1013),
            2 => format!("{}e{}", r % 7, r % 30),
            3 => format!("{}.5", r % 11),
            4 => format!("+{}", r % 5),
            _ => format!("{}", (r % 2001) as f32 / 7.0),
        };
        let (mut v, mut vt, mut vn) = (0i64, 0i64, 0i64);
        let mut text = String::new();
        // Faults are rare, so that many files stay in the fast subset.
        let faulty = next(3) == 0;
        for _ in 0..next(60) + 5 {
            let bad = faulty && next(25) == 0;
            let line = match next(20) {
                0..=6 => {
                    v += 1;
                    let [a, b, c] = [next(10_000), next(10_000), next(10_000)].map(number);
                    match (bad, next(4)) {
                        (true, 0) => format!("v {a} {b}"),
                        (true, 1) => format!("v {a} {b} {c} 0.5"),
                        (true, 2) => format!("v {a} {b} {c} 1 0 0"),
                        (true, _) => format!("v {a} x {c}"),
                        _ => {
                            // Any white space separates words, Unicode's too; mostly
                            // single spaces, the form the reader takes a shorter way.
                            let gaps = [" ", " ", " ", "\t", "  ", "\u{a0}", "\x0c", "\u{3000}"];
                            let [g, h, i] = [next(8), next(8), next(8)].map(|k| gaps[k as usize]);
                            let end = ["", "", " ", "\t"][next(4) as usize];
                            format!("v{g}{a}{h}{b}{i}{c}{end}")
                        }
                    }
                }
                7 => {
                    vt += 1;
                    if bad {
                        "vt 0".to_string()
                    } else {
                        "vt 0.5 0.25 0".to_string()
                    }
                }
                8 => {
                    vn += 1;
                    if bad {
                        "vn 0 1".to_string()
                    } else {
                        "vn 0 0 1".to_string()
                    }
                }
                9..=14 if v > 0 => {
                    let corners = if bad { next(3) } else { 3 + next(4) };
                    let mut line = "f".to_string();
                    for _ in 0..corners {
                        let index = |count: i64, r: u64| match (bad, r % 5) {
                            (true, 0) => "0".to_string(),
                            (true, 1) => (count + 1 + (r % 3) as i64).to_string(),
                            (true, 2) => "x".to_string(),
                            (_, 3) => (-1 - (r as i64 % count.max(1))).to_string(),
                            _ => (1 + r as i64 % count.max(1)).to_string(),
                        };
                        let p = index(v, next(1000));
                        line += &match next(4) {
                            0 if vt > 0 => format!(" {p}/{}", index(vt, next(1000))),
                            1 if vn > 0 => format!(" {p}//{}", index(vn, next(1000))),
                            2 if vt > 0 && vn > 0 => {
                                format!(" {p}/{}/{}", index(vt, next(1000)), index(vn, next(1000)))
                            }
                            _ => format!(" {p}"),
                        };
                    }
                    line
                }
                15 => ["o thing", "g", "g  two words", "o"][next(4) as usize].to_string(),
                16 => ["usemtl red", "usemtl", "mtllib missing.mtl", "s 1"][next(4) as usize]
                    .to_string(),
                17 if bad => "l 1 2".to_string(),
                17 => "# un commentaire été".to_string(),
                18 => String::new(),
                _ => "  \t".to_string(),
            };
            text += &line;
            text += if next(5) == 0 { "\r\n" } else { "\n" };
        }
        text
    }

    #[test]
    fn the_fast_reader_gives_what_tobj_gives_or_declines() {
        let (mut fast, mut faults) = (0, 0);
        for seed in 0..3000 {
            let text = random_obj(seed);
            let reference = parse_with_tobj(text.as_bytes(), Path::new("random.obj"));
            faults += usize::from(reference.is_err());
            // Whole, and in chunks of a few lines, so that relative indices and object
            // breaks cross chunk boundaries.
            for chunk in [usize::MAX, 1 + seed as usize % 40] {
                if let Some(mesh) = fast::parse_in_chunks(text.as_bytes(), chunk) {
                    fast += 1;
                    match &reference {
                        Ok(reference) => assert_eq!(&mesh, reference, "seed {seed}:\n{text}"),
                        Err(e) => panic!("seed {seed}: tobj refuses ({e}) what was read:\n{text}"),
                    }
                }
            }
        }
        // Both paths must be exercised for the test to mean something.
        assert!(fast > 3000, "only {fast} fast reads");
        assert!(faults > 300, "only {faults} faulty files");
    }

    #[test]
    fn files_of_one_object_numbered_in_parallel_read_as_tobj_reads_them() {
        // Without `o` and `g` lines each file is one object, whose vertices the fast
        // reader numbers in parallel over chunks of a few lines.
        let mut fast = 0;
        for seed in 0..2000 {
            let text: String = random_obj(seed)
                .lines()
                .filter(|line| !line.starts_with(['o', 'g']))
                .flat_map(|line| [line, "\n"])
                .collect();
            let Ok(reference) = parse_with_tobj(text.as_bytes(), Path::new("random.obj")) else {
                continue;
            };
            for chunk in [usize::MAX, 1 + seed as usize % 40, 1 + seed as usize % 7] {
                if let Some(mesh) = fast::parse_in_chunks(text.as_bytes(), chunk) {
                    fast += 1;
                    assert_eq!(mesh, reference, "seed {seed}, chunks of {chunk}:\n{text}");
                }
            }
        }
        assert!(fast > 3000, "only {fast} fast reads");
    }

    #[test]
    fn lines_of_the_common_forms_read_as_tobj_reads_them_however_they_end() {
        // The reader's shorter way takes these lines; each one also closes the file, so
        // that it ends at the text's end, in any chunk.
        let lines = [
            "f 1 2 3",
            "f 1 2 3 ",
            "f  1  2  3  4",
            "f 4 3 2 1 ",
            "f 001 2 3",
            "f 1 2 3\r",
            "f 1 2 3 \r",
            "v 1.5 -2 +3.25",
            "v  -.5  0.  7",
            "v 1 2 3 ",
            "v 1 2 3\r",
        ];
        for line in lines {
            for ending in ["", "\n", "\r\n", " \n", "\r\r\n"] {
                let text = format!("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\n{line}{ending}");
                let reference = parse_with_tobj(text.as_bytes(), Path::new("common.obj"));
                let reference = reference.unwrap_or_else(|e| panic!("{text:?}: {e}"));
                for chunk in [usize::MAX, 9, 3] {
                    let mesh = fast::parse_in_chunks(text.as_bytes(), chunk);
                    assert_eq!(
                        mesh.as_ref(),
                        Some(&reference),
                        "{text:?}, chunks of {chunk}"
                    );
                }
            }
        }
    }

    #[test]
    fn the_fast_reader_declines_what_it_does_not_cover() {
        let declined = [
            "v 0 0 0 0.5\n",
            "v 0 0 0 1 0 0\n",
            "v 0 0 0\nv 1 0 0\nl 1 2\n",
            "v 0 0 0\nf 1 1\n",
            "f 1 2 3\nv 0 0 0\nv 1 0 0\nv 0 1 0\n",
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nusemtl\nf 1 2 3\n",
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1/1 2 3\n",
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 0\n",
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n",
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4294967297\n",
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 99999999999999999999\n",
        ];
        for text in declined {
            assert!(fast::parse(text.as_bytes()).is_none(), "{text}");
        }
        assert!(fast::parse(b"v 0 0 0\n\xff\n").is_none());
    }
}
