"""Hydra overrides shared by the tests that train: small, fast, quiet runs."""


#: small, fast, quiet runs: 4 steps of 3-frame windows of 16x16 crops, validation every 2 steps
FAST = ["data=tiny", "net=tiny", "threads=1", "trainer.enable_progress_bar=false", "callbacks.progress=null",
        "trainer.enable_model_summary=false", "trainer.max_steps=4", "trainer.val_check_interval=2",
        "trainer.log_every_n_steps=1", "trainer.limit_val_batches=1", "model.image_interval=2",
        "callbacks.last.every_n_train_steps=2"]
#: a student narrower than net=tiny (the teacher of these tests)
NARROW = ["net.embed.hidden=4", "net.embed.out_channels=4", "net.unet.encoder=[4,6,8]", "net.unet.bottleneck=8",
          "net.unet.decoder=[6,4]", "model.critic.widths=[4,8]"]
