//! The mean of several policies' weights (`stop.average_last`): the run's policy at the end, in
//! place of the learner's last, is the element-wise mean of the newest policies kept in
//! `snapshots/` (every policy an evaluation of the criterion judged). Policies published minutes
//! apart swing in what they avoid; their mean, as in stochastic weight averaging (Izmailov et
//! al. 2018; in deep RL, Nikishin et al. 2018), sits between the swings (docs/experiments.md,
//! "The mean of a run's last policies").

use std::fs;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail, ensure};
use mapless_proto::v1::{NamedTensor, WeightsSnapshot};
use mapless_proto::weights_file::{read_safetensors_file, write_safetensors_file};

/// The metadata key that names the versions a mean was taken over.
pub(crate) const META_AVERAGED_VERSIONS: &str = "averaged_versions";

/// The newest `k` policies in `dir` (files `policy-vN.safetensors`, by N), oldest first; other
/// files are passed over.
pub(crate) fn newest_snapshots(dir: &Path, k: usize) -> Result<Vec<PathBuf>> {
    let mut found: Vec<(u64, PathBuf)> = Vec::new();
    for entry in fs::read_dir(dir).with_context(|| format!("reading {}", dir.display()))? {
        let path = entry?.path();
        let version = path.file_name().and_then(|n| n.to_str()).and_then(|n| n.strip_prefix("policy-v")?.strip_suffix(".safetensors")?.parse().ok());
        if let Some(v) = version {
            found.push((v, path));
        }
    }
    found.sort_by_key(|(v, _)| *v);
    let skip = found.len().saturating_sub(k);
    Ok(found.into_iter().skip(skip).map(|(_, p)| p).collect())
}

/// The element-wise mean of `snapshots`' tensors (summed in f64), with the newest one's version,
/// algorithm, dimensions and metadata, plus [`META_AVERAGED_VERSIONS`] (what tells the mean from
/// the newest policy of that version). A learner restarted without a checkpoint starts afresh
/// while the versions count on, so the newest snapshots of such a run may mix the two. Every snapshot must
/// hold the same tensors, by name and shape, for the same algorithm and dimensions.
pub(crate) fn mean_of(snapshots: &[WeightsSnapshot]) -> Result<WeightsSnapshot> {
    let Some(newest) = snapshots.iter().max_by_key(|s| s.version) else { bail!("no policy to average") };
    for s in snapshots {
        ensure!(
            (s.algorithm, s.obs_dim, s.act_dim, s.tensors.len()) == (newest.algorithm, newest.obs_dim, newest.act_dim, newest.tensors.len()),
            "policies v{} and v{} differ in algorithm, dimensions or tensors: they do not average",
            s.version,
            newest.version
        );
    }
    let mut tensors = Vec::with_capacity(newest.tensors.len());
    for t in &newest.tensors {
        let mut sum = vec![0f64; t.to_f32_vec()?.len()];
        for s in snapshots {
            let other = s.tensor(&t.name).filter(|o| o.shape == t.shape).with_context(|| format!("policy v{} has no tensor `{}` of shape {:?}", s.version, t.name, t.shape))?;
            for (acc, x) in sum.iter_mut().zip(other.to_f32_vec()?) {
                *acc += f64::from(x);
            }
        }
        let n = snapshots.len() as f64;
        let mean: Vec<f32> = sum.iter().map(|x| (x / n) as f32).collect();
        tensors.push(NamedTensor::from_f32(t.name.clone(), t.shape.clone(), &mean)?);
    }
    let mut versions: Vec<u64> = snapshots.iter().map(|s| s.version).collect();
    versions.sort_unstable();
    let mut metadata = newest.metadata.clone();
    metadata.insert(META_AVERAGED_VERSIONS.to_owned(), versions.iter().map(u64::to_string).collect::<Vec<_>>().join(","));
    Ok(WeightsSnapshot { tensors, metadata, ..newest.clone() })
}

/// The mean of the newest `k` policies in `dir`, written to `out`; the versions it averaged, or
/// none when `dir` holds fewer than two policies (nothing to average).
pub(crate) fn average_newest(dir: &Path, k: usize, out: &Path) -> Result<Option<Vec<u64>>> {
    let files = if dir.exists() { newest_snapshots(dir, k)? } else { Vec::new() };
    if files.len() < 2 {
        return Ok(None);
    }
    let snapshots = files.iter().map(|f| read_safetensors_file(f).with_context(|| format!("reading {}", f.display()))).collect::<Result<Vec<_>>>()?;
    let mean = mean_of(&snapshots)?;
    write_safetensors_file(out, &mean).with_context(|| format!("writing {}", out.display()))?;
    let mut versions: Vec<u64> = snapshots.iter().map(|s| s.version).collect();
    versions.sort_unstable();
    Ok(Some(versions))
}

#[cfg(test)]
mod tests {
    use super::*;
    use mapless_proto::v1::{Algorithm, ProtocolVersion};

    fn snapshot(version: u64, w: &[f32], b: f32) -> WeightsSnapshot {
        WeightsSnapshot {
            protocol_version: ProtocolVersion::V1 as i32,
            version,
            algorithm: Algorithm::Sac as i32,
            created_unix_ms: version,
            obs_dim: 2,
            act_dim: 1,
            tensors: vec![NamedTensor::from_f32("actor.l0.weight", vec![1, 2], w).unwrap(), NamedTensor::from_f32("actor.l0.bias", vec![1], &[b]).unwrap()],
            metadata: [("run".to_owned(), format!("r{version}"))].into(),
        }
    }

    #[test]
    fn the_mean_is_element_wise_and_keeps_the_newest_ones_identity() {
        let mean = mean_of(&[snapshot(7, &[1.0, -2.0], 0.5), snapshot(9, &[3.0, 2.0], 1.5), snapshot(8, &[2.0, 3.0], -2.0)]).unwrap();
        assert_eq!(mean.tensor("actor.l0.weight").unwrap().to_f32_vec().unwrap(), [2.0, 1.0]);
        assert_eq!(mean.tensor("actor.l0.bias").unwrap().to_f32_vec().unwrap(), [0.0]);
        assert_eq!((mean.version, mean.created_unix_ms), (9, 9));
        assert_eq!((mean.metadata["run"].as_str(), mean.metadata[META_AVERAGED_VERSIONS].as_str()), ("r9", "7,8,9"));
        assert!(mean.validate().is_ok());
    }

    #[test]
    fn policies_that_differ_in_shape_or_tensors_do_not_average() {
        let mut other = snapshot(8, &[1.0, 1.0], 0.0);
        other.tensors[0] = NamedTensor::from_f32("actor.l0.weight", vec![2, 1], &[1.0, 1.0]).unwrap();
        let e = format!("{:#}", mean_of(&[snapshot(7, &[1.0, 2.0], 0.0), other]).unwrap_err());
        assert!(e.contains("actor.l0.weight"), "{e}");
        let mut fewer = snapshot(8, &[1.0, 1.0], 0.0);
        fewer.tensors.pop();
        assert!(mean_of(&[snapshot(7, &[1.0, 2.0], 0.0), fewer]).is_err());
        let mut obs = snapshot(8, &[1.0, 1.0], 0.0);
        obs.obs_dim = 3;
        assert!(mean_of(&[snapshot(7, &[1.0, 2.0], 0.0), obs]).is_err());
        assert!(mean_of(&[]).is_err());
    }

    #[test]
    fn the_newest_snapshots_by_version_are_averaged_and_one_is_nothing_to_average() {
        let dir = tempfile::tempdir().unwrap();
        let (snaps, out) = (dir.path().join("snapshots"), dir.path().join("policy-average.safetensors"));
        assert_eq!(average_newest(&snaps, 3, &out).unwrap(), None, "no snapshots/ yet");
        fs::create_dir(&snaps).unwrap();
        for (v, w) in [(10, 100.0), (9, 1.0), (200, 4.0), (11, 7.0)] {
            write_safetensors_file(&snaps.join(format!("policy-v{v}.safetensors")), &snapshot(v, &[w, w], w)).unwrap();
        }
        fs::write(snaps.join("notes.txt"), "not a policy").unwrap();
        let names = |k| newest_snapshots(&snaps, k).unwrap().iter().map(|p| p.file_name().unwrap().to_string_lossy().into_owned()).collect::<Vec<_>>();
        assert_eq!(names(3), ["policy-v10.safetensors", "policy-v11.safetensors", "policy-v200.safetensors"], "by version, not by name");
        assert_eq!(names(9).len(), 4);
        assert_eq!(average_newest(&snaps, 2, &out).unwrap(), Some(vec![11, 200]));
        let mean = read_safetensors_file(&out).unwrap();
        assert_eq!((mean.version, mean.tensor("actor.l0.bias").unwrap().to_f32_vec().unwrap()), (200, vec![5.5]));
        assert_eq!(average_newest(&snaps, 1, &out).unwrap(), None, "one policy is nothing to average");
    }
}
