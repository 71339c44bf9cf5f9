//! Staging the public recordings' frames (`shoal eval stage-real`) and
//! checking what is staged (`shoal eval real`, before it measures).
//!
//! Each manifest with a `fetch` block names a GitHub repository, a commit,
//! and per frame file its path there and its SHA-256. Staging copies each
//! file out of that commit with `git` — from a local mirror when one is
//! given (`MIRRORS/<owner>+<name>/repo`, or a bare `<owner>+<name>.git`),
//! else from a blob-less clone of `https://github.com/<owner>/<name>` kept
//! in `DATA/.git-cache/` — and refuses a file whose hash differs from the
//! manifest's. Nothing is fetched at test time.

use super::manifest::{load_manifest, Fetch, Manifest, MANIFEST_DIR};
use crate::eval::EvalError;
use sha2::{Digest, Sha256};
use std::path::{Path, PathBuf};
use std::process::Command;

/// What staging did for one recording.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Staged {
    pub recording: String,
    /// Files written now.
    pub written: usize,
    /// Files already there with the right hash.
    pub present: usize,
}

/// The SHA-256 of `bytes`, as lowercase hex.
pub fn sha256_hex(bytes: &[u8]) -> String {
    Sha256::digest(bytes)
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

/// Check the staged files of `m` under `dir` against the manifest's hashes.
/// A recording without a `fetch` block (your own, with its `eval.json`) is
/// not checked.
pub fn verify_staged(m: &Manifest, dir: &Path) -> Result<(), EvalError> {
    let Some(fetch) = &m.fetch else {
        return Ok(());
    };
    for f in &fetch.files {
        let path = dir.join(&f.file);
        let bytes = std::fs::read(&path).map_err(|source| EvalError::Io {
            path: path.clone(),
            source,
        })?;
        let got = sha256_hex(&bytes);
        if got != f.sha256 {
            return Err(EvalError::Setup(format!(
                "{}: SHA-256 {got} is not the manifest's {} ({}@{}:{}); re-stage it with `shoal eval stage-real`",
                path.display(),
                f.sha256,
                fetch.repo,
                &fetch.commit[..12],
                f.path
            )));
        }
    }
    Ok(())
}

/// Stage every manifest of `manifests` that has a `fetch` block into
/// `root/<folder>/`, taking the repositories from `mirrors` when given.
/// `progress` hears one line per recording. A recording that cannot be
/// staged (no mirror, a failed clone, a hash that does not match) does not
/// stop the others: they are staged, and the error then names every one
/// that was not, and why.
pub fn stage_all(
    root: &Path,
    manifests: &Path,
    mirrors: Option<&Path>,
    progress: &mut dyn FnMut(&str),
) -> Result<Vec<Staged>, EvalError> {
    let mut paths: Vec<PathBuf> = std::fs::read_dir(manifests)
        .map_err(|source| EvalError::Io {
            path: manifests.to_path_buf(),
            source,
        })?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "json"))
        .collect();
    paths.sort();
    let (mut done, mut failed) = (Vec::new(), Vec::new());
    for path in paths {
        let m = load_manifest(&path)?;
        let Some(fetch) = &m.fetch else {
            progress(&format!("{}: no `fetch` block, not staged", path.display()));
            continue;
        };
        let stem = path.file_stem().map(|s| s.to_string_lossy().into_owned());
        let folder = m.folder.clone().or(stem).unwrap_or_default();
        let dir = root.join(folder);
        match stage_one(&m.name, fetch, &dir, root, mirrors) {
            Ok(staged) => {
                progress(&format!(
                    "{}: {} written, {} already staged ({}@{})",
                    staged.recording,
                    staged.written,
                    staged.present,
                    fetch.repo,
                    &fetch.commit[..12]
                ));
                done.push(staged);
            }
            Err(e) => {
                // An empty folder left behind would read as a staged recording.
                let _ = std::fs::remove_dir(&dir);
                let why = match e {
                    EvalError::Setup(why) => why,
                    other => other.to_string(),
                };
                progress(&format!("{}: NOT staged: {why}", m.name));
                failed.push(format!("{}: {why}", m.name));
            }
        }
    }
    if failed.is_empty() {
        Ok(done)
    } else {
        Err(EvalError::Setup(format!(
            "{} of {} recordings not staged (the {} others are): {}",
            failed.len(),
            failed.len() + done.len(),
            done.len(),
            failed.join("; ")
        )))
    }
}

/// The default manifests folder, for the CLI.
pub fn manifest_dir() -> &'static Path {
    Path::new(MANIFEST_DIR)
}

fn stage_one(
    name: &str,
    fetch: &Fetch,
    dir: &Path,
    root: &Path,
    mirrors: Option<&Path>,
) -> Result<Staged, EvalError> {
    let io = |path: &Path| {
        let path = path.to_path_buf();
        move |source| EvalError::Io { path, source }
    };
    std::fs::create_dir_all(dir).map_err(io(dir))?;
    let mut staged = Staged {
        recording: name.to_string(),
        written: 0,
        present: 0,
    };
    let mut git_dir = None;
    for f in &fetch.files {
        let dest = dir.join(&f.file);
        if std::fs::read(&dest).is_ok_and(|b| sha256_hex(&b) == f.sha256) {
            staged.present += 1;
            continue;
        }
        if git_dir.is_none() {
            git_dir = Some(repository(fetch, root, mirrors)?);
        }
        let git = git_dir.as_deref().unwrap_or(Path::new("."));
        let bytes = git_output(
            git,
            &["show", &format!("{}:{}", fetch.commit, f.path)],
            &format!("{}@{}:{}", fetch.repo, &fetch.commit[..12], f.path),
        )?;
        let got = sha256_hex(&bytes);
        if got != f.sha256 {
            return Err(EvalError::Setup(format!(
                "{}@{}:{}: SHA-256 {got}, the manifest of {name} says {} (not written)",
                fetch.repo,
                &fetch.commit[..12],
                f.path,
                f.sha256
            )));
        }
        std::fs::write(&dest, &bytes).map_err(io(&dest))?;
        staged.written += 1;
    }
    Ok(staged)
}

/// A git directory holding `fetch.commit`: a mirror's, or the cache's
/// blob-less clone (made or updated here).
fn repository(fetch: &Fetch, root: &Path, mirrors: Option<&Path>) -> Result<PathBuf, EvalError> {
    let key = fetch.repo.replace('/', "+");
    if let Some(m) = mirrors {
        for candidate in [m.join(&key).join("repo"), m.join(format!("{key}.git"))] {
            if candidate.is_dir() {
                return Ok(candidate);
            }
        }
        return Err(EvalError::Setup(format!(
            "no mirror of {} under {} (looked for {key}/repo and {key}.git)",
            fetch.repo,
            m.display()
        )));
    }
    let cache = root.join(".git-cache").join(format!("{key}.git"));
    let url = format!("https://github.com/{}", fetch.repo);
    if !cache.is_dir() {
        let parent = cache.parent().unwrap_or(root);
        std::fs::create_dir_all(parent).map_err(|source| EvalError::Io {
            path: parent.to_path_buf(),
            source,
        })?;
        let target = cache.to_string_lossy().into_owned();
        git_output(
            parent,
            &["clone", "--bare", "--filter=blob:none", &url, &target],
            &url,
        )?;
    }
    let has_commit = git_output(
        &cache,
        &["cat-file", "-e", &format!("{}^{{commit}}", fetch.commit)],
        &url,
    )
    .is_ok();
    if !has_commit {
        git_output(&cache, &["fetch", "origin", &fetch.commit], &url)?;
    }
    Ok(cache)
}

/// Run `git` in `dir` and return its standard output; a failure names
/// `what` and carries git's own message.
fn git_output(dir: &Path, args: &[&str], what: &str) -> Result<Vec<u8>, EvalError> {
    let out = Command::new("git")
        .arg("-C")
        .arg(dir)
        .args(args)
        .output()
        .map_err(|e| EvalError::Setup(format!("{what}: cannot run git: {e}")))?;
    if !out.status.success() {
        return Err(EvalError::Setup(format!(
            "{what}: git {} failed: {}",
            args.first().copied().unwrap_or(""),
            String::from_utf8_lossy(&out.stderr).trim()
        )));
    }
    Ok(out.stdout)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn git(dir: &Path, args: &[&str]) {
        let ok = Command::new("git")
            .arg("-C")
            .arg(dir)
            .args(args)
            .env("GIT_AUTHOR_NAME", "t")
            .env("GIT_AUTHOR_EMAIL", "t@t")
            .env("GIT_COMMITTER_NAME", "t")
            .env("GIT_COMMITTER_EMAIL", "t@t")
            .status()
            .expect("git runs")
            .success();
        assert!(ok, "git {args:?}");
    }

    #[test]
    fn sha256_of_known_input() {
        assert_eq!(
            sha256_hex(b"abc"),
            "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad"
        );
    }

    /// A mirror with one commit: staging writes the file, a second run finds
    /// it staged, a damaged staged file fails the check and is re-staged, and
    /// a manifest whose hash is wrong writes nothing.
    #[test]
    fn stages_from_a_mirror_and_checks_hashes() {
        let tmp = std::env::temp_dir().join(format!("shoal-stage-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&tmp);
        let repo = tmp.join("mirrors/someone+frames/repo");
        std::fs::create_dir_all(repo.join("pics")).unwrap();
        git(&repo, &["init", "-q"]);
        std::fs::write(repo.join("pics/a.jpg"), b"frame bytes").unwrap();
        git(&repo, &["add", "."]);
        git(&repo, &["commit", "-q", "-m", "x"]);
        let commit = String::from_utf8(
            Command::new("git")
                .arg("-C")
                .arg(&repo)
                .args(["rev-parse", "HEAD"])
                .output()
                .unwrap()
                .stdout,
        )
        .unwrap()
        .trim()
        .to_string();
        let manifests = tmp.join("manifests");
        std::fs::create_dir_all(&manifests).unwrap();
        let manifest = |sha: &str| {
            format!(
                r#"{{"name": "rec", "underwater": false, "codes": "apriltag36h11", "side_m": 0.1,
                "images": ["a.jpg"], "splits": {{"dev": [0, 1]}},
                "truth": {{"rotation_steps": {{"id": 1, "angle_deg": {{"a.jpg": 0}}}}}},
                "fetch": {{"repo": "someone/frames", "commit": "{commit}",
                           "files": [{{"file": "a.jpg", "path": "pics/a.jpg", "sha256": "{sha}"}}]}}}}"#
            )
        };
        let good = sha256_hex(b"frame bytes");
        std::fs::write(manifests.join("rec.json"), manifest(&good)).unwrap();
        let data = tmp.join("data");
        let mirrors = tmp.join("mirrors");
        let mut lines = Vec::new();
        let run = |lines: &mut Vec<String>| {
            stage_all(&data, &manifests, Some(&mirrors), &mut |l| {
                lines.push(l.to_string())
            })
        };
        let first = run(&mut lines).unwrap();
        assert_eq!((first[0].written, first[0].present), (1, 0));
        assert_eq!(
            std::fs::read(data.join("rec/a.jpg")).unwrap(),
            b"frame bytes"
        );
        let again = run(&mut lines).unwrap();
        assert_eq!((again[0].written, again[0].present), (0, 1));

        let m = load_manifest(&manifests.join("rec.json")).unwrap();
        verify_staged(&m, &data.join("rec")).unwrap();
        std::fs::write(data.join("rec/a.jpg"), b"frame bytez").unwrap();
        let err = verify_staged(&m, &data.join("rec"))
            .unwrap_err()
            .to_string();
        assert!(err.contains("a.jpg") && err.contains(&good), "{err}");
        let healed = run(&mut lines).unwrap();
        assert_eq!(healed[0].written, 1);

        std::fs::remove_file(data.join("rec/a.jpg")).unwrap();
        std::fs::write(manifests.join("rec.json"), manifest(&"0".repeat(64))).unwrap();
        let err = run(&mut lines).unwrap_err().to_string();
        assert!(
            err.contains("pics/a.jpg") && err.contains("not written"),
            "{err}"
        );
        assert!(!data.join("rec/a.jpg").exists());

        let err = stage_all(&data, &manifests, Some(&tmp.join("nowhere")), &mut |_| {})
            .unwrap_err()
            .to_string();
        assert!(err.contains("no mirror of someone/frames"), "{err}");

        // A recording whose source is missing does not stop the others
        // (the manifests are taken in name order: the missing one first).
        std::fs::write(manifests.join("rec.json"), manifest(&good)).unwrap();
        std::fs::write(
            manifests.join("a-missing.json"),
            manifest(&good)
                .replace("\"rec\"", "\"gone\"")
                .replace("someone/frames", "someone/elsewhere"),
        )
        .unwrap();
        std::fs::remove_dir_all(&data).unwrap();
        let mut lines = Vec::new();
        let err = run(&mut lines).unwrap_err().to_string();
        assert!(
            err.contains("1 of 2 recordings not staged")
                && err.contains("gone: ")
                && err.contains("no mirror of someone/elsewhere"),
            "{err}"
        );
        assert_eq!(
            std::fs::read(data.join("rec/a.jpg")).unwrap(),
            b"frame bytes"
        );
        assert!(
            !data.join("a-missing").exists(),
            "no empty folder left behind"
        );
        assert!(
            lines.iter().any(|l| l.starts_with("gone: NOT staged"))
                && lines.iter().any(|l| l.starts_with("rec: 1 written")),
            "{lines:?}"
        );
        let _ = std::fs::remove_dir_all(&tmp);
    }

    #[test]
    fn bad_fetch_blocks_are_refused_with_the_field() {
        let f = |repo: &str, commit: &str, file: &str, path: &str, sha: &str| Fetch {
            repo: repo.into(),
            commit: commit.into(),
            files: vec![super::super::manifest::FetchFile {
                file: file.into(),
                path: path.into(),
                sha256: sha.into(),
            }],
        };
        let c = "a".repeat(40);
        let s = "b".repeat(64);
        assert_eq!(f("o/n", &c, "x.jpg", "d/x.jpg", &s).problem(), None);
        for (bad, field) in [
            (f("o", &c, "x.jpg", "x.jpg", &s), "fetch.repo"),
            (f("o/../n", &c, "x.jpg", "x.jpg", &s), "fetch.repo"),
            (f("o/n", "abc", "x.jpg", "x.jpg", &s), "fetch.commit"),
            (f("o/n", &c, "../x.jpg", "x.jpg", &s), "plain file name"),
            (f("o/n", &c, "x.jpg", "../x.jpg", &s), "relative"),
            (f("o/n", &c, "x.jpg", "x.jpg", "zz"), "sha256"),
        ] {
            let p = bad.problem().expect("refused");
            assert!(p.contains(field), "{p}");
        }
    }
}
