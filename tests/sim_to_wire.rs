//! The simulator's vectorised output becomes the wire contract's columnar batch without loss:
//! dimensions, rewards, and terminal vs truncated flags survive encode/decode and validate.

use mapless_proto::v1::TransitionBatch;
use mapless_proto::{Transition, TransitionBatchBuilder};
use mapless_sim::{EnvConfig, Map, VecEnv, VecStep, World};
use prost::Message;

#[test]
fn vec_env_steps_encode_as_a_valid_columnar_batch_with_distinct_end_flags() {
    let mut cfg = EnvConfig::default();
    cfg.episode.max_steps = 40; // short episodes so truncations happen
    let world = World::new(Map::builtin("env2").unwrap(), cfg).unwrap();
    let (n, d) = (16usize, world.obs_dim());
    let mut env = VecEnv::new(world, n, 7).unwrap();
    let mut out = VecStep::default();
    let mut b = TransitionBatchBuilder::new(d, 2);
    let (mut terminals, mut truncations) = (0, 0);
    for t in 0..120u32 {
        let obs = env.obs().to_vec();
        // Full speed with a steady turn: some vehicles hit walls, the rest reach the limit.
        let actions: Vec<f32> = (0..n).flat_map(|i| [1.0, if i % 2 == 0 { 0.0 } else { 0.7 }]).collect();
        env.step(&actions, &mut out).unwrap();
        for i in 0..n {
            terminals += out.terminal[i] as usize;
            truncations += out.truncated[i] as usize;
            b.push(Transition {
                obs: &obs[i * d..(i + 1) * d],
                action: &actions[2 * i..2 * i + 2],
                reward: out.reward[i],
                next_obs: &out.next_obs[i * d..(i + 1) * d],
                terminal: out.terminal[i],
                truncated: out.truncated[i],
                episode_id: env.envs()[i].episode_id(),
                step: t,
                policy_version: 0,
            })
            .unwrap();
        }
    }
    assert!(terminals > 0 && truncations > 0, "need both kinds of ends: {terminals} terminal, {truncations} truncated");
    let batch = b.finish("actor-0", 1);
    let bytes = batch.encode_to_vec();
    let back = TransitionBatch::decode(bytes.as_slice()).unwrap();
    assert_eq!(back.validate(d, 2, 1 << 20).unwrap(), n * 120);
    let (mut term_back, mut trunc_back) = (0, 0);
    for row in back.iter_rows() {
        assert!(!(row.terminal && row.truncated));
        term_back += row.terminal as usize;
        trunc_back += row.truncated as usize;
        assert_eq!(row.obs.len(), d);
    }
    assert_eq!((term_back, trunc_back), (terminals, truncations));
    assert_eq!(back, batch);
}
