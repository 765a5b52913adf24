/* Pty mode of the stage harness: UART0 on a pseudo-terminal, paced to the wall clock. */
#define _GNU_SOURCE
#include <errno.h>
#include <fcntl.h>
#include <pty.h>
#include <stdio.h>
#include <string.h>
#include <termios.h>
#include <time.h>
#include <unistd.h>

#include <simavr/avr_uart.h>

#include "harness.h"

static double wall_s(void)
{
	struct timespec ts;
	clock_gettime(CLOCK_MONOTONIC, &ts);
	return ts.tv_sec + ts.tv_nsec * 1e-9;
}

static void report(double t)
{
	printf("t %.6f", t);
	for (int i = 0; i < n_axes; i++)
		printf(" %ld", axes[i].count);
	printf("\n");
	fflush(stdout);
}

static int open_pty(const char *link)
{
	int slave;
	char name[256];
	struct termios tio;
	if (openpty(&pty_master, &slave, name, NULL, NULL) < 0)
		return -1;
	cfmakeraw(&tio);
	tcsetattr(slave, TCSANOW, &tio);
	/* keep the slave open: a host closing the port must not hang the master up */
	fcntl(pty_master, F_SETFL, fcntl(pty_master, F_GETFL) | O_NONBLOCK);
	if (link) {
		unlink(link);
		if (symlink(name, link) < 0)
			return -1;
	}
	printf("pty %s\n", name);
	fflush(stdout);
	return 0;
}

int run_pty(const char *link, double speed)
{
	if (open_pty(link) < 0) {
		perror("stage_harness: pty");
		return 2;
	}
	fcntl(0, F_SETFL, fcntl(0, F_GETFL) | O_NONBLOCK);

	double wall0 = wall_s(), last_report = -1.0;
	int state = cpu_Running;
	avr_irq_t *uart_in = avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_INPUT);
	uint8_t inbuf[256];
	size_t in_len = 0, in_pos = 0;
	char cmd[64];
	while (!stop_requested && state != cpu_Done && state != cpu_Crashed) {
		for (int k = 0; k < 2000 && state != cpu_Done && state != cpu_Crashed; k++)
			state = avr_run(avr);
		double t = (double)avr->cycle / avr->frequency;
		if (in_pos == in_len && pty_master >= 0) {  /* bytes from the host */
			ssize_t got = read(pty_master, inbuf, sizeof(inbuf));
			in_len = got > 0 ? (size_t)got : 0;
			in_pos = 0;
		}
		while (in_pos < in_len && uart_xon)
			avr_raise_irq(uart_in, inbuf[in_pos++]);
		if ((counts_changed && t - last_report >= 1e-3) || t - last_report >= 0.05) {
			report(t);
			last_report = t;
			counts_changed = 0;
		}
		ssize_t c = read(0, cmd, sizeof(cmd) - 1);
		if (c > 0 && !strncmp(cmd, "quit", 4))
			break;
		if (speed > 0) {  /* no faster than `speed` x real time */
			double ahead = t / speed - (wall_s() - wall0);
			if (ahead > 0.002)
				usleep((useconds_t)(ahead * 1e6));
		}
	}
	report((double)avr->cycle / avr->frequency);
	printf("exit %d\n", state);
	fflush(stdout);
	if (link)
		unlink(link);
	avr_terminate(avr);
	return 0;
}
