//! Evaluation metrics that judge a set of images rather than the avatar that made them:
//! FID (`fid`: pytorch-fid's Inception-v3 on the CPU and the Fréchet distance) and its
//! weights file (`fid_weights`). They live outside `avatar` because nothing in them
//! knows an avatar: `avatar::eval` renders the held-out frames and hands the images
//! here. (The per-image metrics, PSNR, SSIM and LPIPS, stay in `avatar::eval`, which
//! computes them frame by frame as it renders.)

pub mod fid;
pub mod fid_weights;
